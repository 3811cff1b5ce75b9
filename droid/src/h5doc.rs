//! An HDF5 file as plain data: datasets by path, root attributes by name.
//!
//! DROID's trajectory.h5 is a tree of groups whose leaves are arrays with the step as their
//! first axis (float64, int64 timestamps, bool flags), plus a few root attributes. [`H5Doc`]
//! holds exactly that, so the DROID mapping (`crate::droid`) never touches HDF5 and two files
//! compare with `==`. Files are written without object modification times, so the same
//! content gives the same bytes.

use hdf5::types::{TypeDescriptor, VarLenAscii, VarLenUnicode};
use hdf5_metno as hdf5;
use std::collections::BTreeMap;
use std::path::Path;
use std::str::FromStr;

/// One dataset's values, row-major.
#[derive(Debug, Clone, PartialEq)]
pub enum Data {
    F64(Vec<f64>),
    I64(Vec<i64>),
    Bool(Vec<bool>),
}

impl Data {
    pub fn len(&self) -> usize {
        match self {
            Data::F64(v) => v.len(),
            Data::I64(v) => v.len(),
            Data::Bool(v) => v.len(),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    pub fn dtype(&self) -> &'static str {
        match self {
            Data::F64(_) => "float64",
            Data::I64(_) => "int64",
            Data::Bool(_) => "bool",
        }
    }
}

/// A dataset: its shape (first axis = steps) and values.
#[derive(Debug, Clone, PartialEq)]
pub struct Column {
    pub shape: Vec<usize>,
    pub data: Data,
}

impl Column {
    /// `rows` rows of `width` float64 each (`width` 0: a 1-D column).
    pub fn f64_rows(rows: usize, width: usize, data: Vec<f64>) -> Column {
        let shape = if width == 0 { vec![rows] } else { vec![rows, width] };
        Column { shape, data: Data::F64(data) }
    }
}

/// A root attribute.
#[derive(Debug, Clone, PartialEq)]
pub enum Attr {
    Str(String),
    Bool(bool),
    I64(i64),
    F64(f64),
}

/// The content of an HDF5 file as far as DROID uses it.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct H5Doc {
    /// `observation/robot_state/joint_positions` -> column.
    pub datasets: BTreeMap<String, Column>,
    pub attrs: BTreeMap<String, Attr>,
    /// Datasets read but not held (strings, images, compound types): path and type.
    pub skipped: Vec<String>,
}

#[derive(Debug, thiserror::Error)]
pub enum H5Error {
    #[error("{path}: {what}: {source}")]
    Hdf5 { path: String, what: String, source: hdf5::Error },
    #[error("{path}: dataset `{dataset}` has shape {shape:?} but {values} values")]
    Shape { path: String, dataset: String, shape: Vec<usize>, values: usize },
    #[error(
        "{path}: dataset `{dataset}` claims shape {shape:?} ({values} values), more than the {MAX_VALUES} a trajectory holds: a damaged file?"
    )]
    TooLarge { path: String, dataset: String, shape: Vec<usize>, values: usize },
}

/// The most values one dataset may claim before it is read (a DROID trajectory.h5 holds a few
/// thousand steps of a few dozen numbers; a damaged header can claim 10^10 and the read would
/// try to allocate them).
pub const MAX_VALUES: usize = 1 << 26;

fn err(path: &Path, what: impl Into<String>) -> impl FnOnce(hdf5::Error) -> H5Error {
    let path = path.display().to_string();
    let what = what.into();
    move |source| H5Error::Hdf5 { path, what, source }
}

/// Writes `doc` to `path` (replacing it).
pub fn write(path: &Path, doc: &H5Doc) -> Result<(), H5Error> {
    let file = hdf5::File::with_options()
        .with_fcpl(|p| p.obj_track_times(false))
        .create(path)
        .map_err(err(path, "creating the file"))?;
    let mut groups: BTreeMap<String, hdf5::Group> = BTreeMap::new();
    for (name, col) in &doc.datasets {
        let n: usize = col.shape.iter().product();
        if n != col.data.len() {
            return Err(H5Error::Shape {
                path: path.display().to_string(),
                dataset: name.clone(),
                shape: col.shape.clone(),
                values: col.data.len(),
            });
        }
        let (parent, leaf) = name.rsplit_once('/').unwrap_or(("", name.as_str()));
        let group = group_for(&file, &mut groups, parent, path)?;
        let what = format!("writing `{name}`");
        let shape = col.shape.clone();
        let ds = match &col.data {
            Data::F64(v) => new_dataset::<f64>(&group, shape, leaf).and_then(|d| d.write_raw(v.as_slice()).map(|_| d)),
            Data::I64(v) => new_dataset::<i64>(&group, shape, leaf).and_then(|d| d.write_raw(v.as_slice()).map(|_| d)),
            Data::Bool(v) => {
                new_dataset::<bool>(&group, shape, leaf).and_then(|d| d.write_raw(v.as_slice()).map(|_| d))
            }
        };
        ds.map_err(err(path, what))?;
    }
    for (name, a) in &doc.attrs {
        let what = format!("writing attribute `{name}`");
        let r = match a {
            Attr::Str(s) => match VarLenUnicode::from_str(s) {
                Ok(v) => file.new_attr::<VarLenUnicode>().create(name.as_str()).and_then(|x| x.write_scalar(&v)),
                Err(e) => Err(hdf5::Error::from(format!("{e}").as_str())),
            },
            Attr::Bool(b) => file.new_attr::<bool>().create(name.as_str()).and_then(|x| x.write_scalar(b)),
            Attr::I64(i) => file.new_attr::<i64>().create(name.as_str()).and_then(|x| x.write_scalar(i)),
            Attr::F64(f) => file.new_attr::<f64>().create(name.as_str()).and_then(|x| x.write_scalar(f)),
        };
        r.map_err(err(path, what))?;
    }
    file.close().map_err(err(path, "closing the file"))
}

fn new_dataset<T: hdf5::H5Type>(group: &hdf5::Group, shape: Vec<usize>, name: &str) -> hdf5::Result<hdf5::Dataset> {
    group.new_dataset::<T>().shape(shape).obj_track_times(false).create(name)
}

fn group_for(
    file: &hdf5::File,
    groups: &mut BTreeMap<String, hdf5::Group>,
    path: &str,
    file_path: &Path,
) -> Result<hdf5::Group, H5Error> {
    if path.is_empty() {
        return file.as_group().map_err(err(file_path, "opening the root group"));
    }
    if let Some(g) = groups.get(path) {
        return Ok(g.clone());
    }
    let (parent, leaf) = path.rsplit_once('/').unwrap_or(("", path));
    let up = group_for(file, groups, parent, file_path)?;
    let g = up
        .create_group_builder()
        .obj_track_times(false)
        .create(leaf)
        .map_err(err(file_path, format!("creating group `{path}`")))?;
    groups.insert(path.to_owned(), g.clone());
    Ok(g)
}

/// Reads every numeric and bool dataset and the root attributes of `path`.
pub fn read(path: &Path) -> Result<H5Doc, H5Error> {
    let file = hdf5::File::open(path).map_err(err(path, "opening it as HDF5"))?;
    let mut doc = H5Doc::default();
    let root = file.as_group().map_err(err(path, "opening the root group"))?;
    read_group(&root, "", &mut doc, path)?;
    for name in file.attr_names().map_err(err(path, "listing attributes"))? {
        let a = file.attr(&name).map_err(err(path, format!("attribute `{name}`")))?;
        let what = format!("reading attribute `{name}`");
        let desc = a.dtype().and_then(|t| t.to_descriptor()).map_err(err(path, what.clone()))?;
        let value = match desc {
            TypeDescriptor::VarLenUnicode => a.read_scalar::<VarLenUnicode>().map(|s| Attr::Str(s.as_str().to_owned())),
            TypeDescriptor::VarLenAscii => a.read_scalar::<VarLenAscii>().map(|s| Attr::Str(s.as_str().to_owned())),
            TypeDescriptor::Boolean => a.read_scalar::<bool>().map(Attr::Bool),
            TypeDescriptor::Integer(_) | TypeDescriptor::Unsigned(_) => a.read_scalar::<i64>().map(Attr::I64),
            TypeDescriptor::Float(_) => a.read_scalar::<f64>().map(Attr::F64),
            other => {
                doc.skipped.push(format!("@{name} ({other})"));
                continue;
            }
        };
        doc.attrs.insert(name, value.map_err(err(path, what))?);
    }
    Ok(doc)
}

fn read_group(group: &hdf5::Group, prefix: &str, doc: &mut H5Doc, path: &Path) -> Result<(), H5Error> {
    for name in group.member_names().map_err(err(path, format!("listing `{prefix}`")))? {
        let full = if prefix.is_empty() { name.clone() } else { format!("{prefix}/{name}") };
        if let Ok(g) = group.group(&name) {
            read_group(&g, &full, doc, path)?;
            continue;
        }
        let Ok(ds) = group.dataset(&name) else {
            doc.skipped.push(format!("{full} (not a group or dataset)"));
            continue;
        };
        let what = format!("reading `{full}`");
        let desc = ds.dtype().and_then(|t| t.to_descriptor()).map_err(err(path, what.clone()))?;
        let shape = ds.shape();
        let values = shape.iter().try_fold(1usize, |n, &d| n.checked_mul(d)).unwrap_or(usize::MAX);
        if values > MAX_VALUES {
            return Err(H5Error::TooLarge { path: path.display().to_string(), dataset: full, shape, values });
        }
        let data = match desc {
            TypeDescriptor::Float(_) => ds.read_raw::<f64>().map(Data::F64),
            TypeDescriptor::Integer(_) | TypeDescriptor::Unsigned(_) => ds.read_raw::<i64>().map(Data::I64),
            TypeDescriptor::Boolean => ds.read_raw::<bool>().map(Data::Bool),
            other => {
                doc.skipped.push(format!("{full} ({other})"));
                continue;
            }
        };
        doc.datasets.insert(full, Column { shape, data: data.map_err(err(path, what))? });
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Found by the property tests (a bit flip in a dataset's header): a dataset claiming 10^10
    /// values made the read allocate 80 GB and abort the process. Refused by name instead.
    #[test]
    fn a_dataset_claiming_ten_billion_values_is_refused_not_allocated() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("huge.h5");
        {
            let f = hdf5::File::create(&path).unwrap();
            // Chunked and never written: a small file whose header claims 10^10 values.
            f.new_dataset::<f64>().chunk(1024).shape(10_000_000_000usize).create("action/huge").unwrap();
        }
        assert!(std::fs::metadata(&path).unwrap().len() < 100_000);
        let e = read(&path).unwrap_err();
        assert!(matches!(e, H5Error::TooLarge { values: 10_000_000_000, .. }), "{e}");
        assert!(e.to_string().contains("action/huge") && e.to_string().contains("huge.h5"), "{e}");
    }

    #[test]
    fn a_document_round_trips_bytes_included() {
        let dir = tempfile::tempdir().unwrap();
        let mut doc = H5Doc::default();
        doc.datasets.insert("a/b/x".into(), Column::f64_rows(2, 3, vec![1.0, 2.0, 3.0, 4.0, 5.0, f64::MIN_POSITIVE]));
        doc.datasets.insert("a/t".into(), Column { shape: vec![2], data: Data::I64(vec![-1, i64::MAX]) });
        doc.datasets.insert("c".into(), Column { shape: vec![2], data: Data::Bool(vec![true, false]) });
        doc.attrs.insert("user".into(), Attr::Str("ünïcode".into()));
        doc.attrs.insert("success".into(), Attr::Bool(true));
        let (p1, p2) = (dir.path().join("1.h5"), dir.path().join("2.h5"));
        write(&p1, &doc).unwrap();
        assert_eq!(read(&p1).unwrap(), doc);
        std::thread::sleep(std::time::Duration::from_millis(1100));
        write(&p2, &doc).unwrap();
        assert_eq!(std::fs::read(&p1).unwrap(), std::fs::read(&p2).unwrap(), "same content, same bytes");
    }

    #[test]
    fn a_shape_that_does_not_fit_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let mut doc = H5Doc::default();
        doc.datasets.insert("x".into(), Column::f64_rows(2, 3, vec![1.0]));
        let e = write(&dir.path().join("x.h5"), &doc).unwrap_err().to_string();
        assert!(e.contains("`x` has shape [2, 3] but 1 values"), "{e}");
    }

    #[test]
    fn a_file_that_is_not_hdf5_is_named() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("t.h5");
        std::fs::write(&p, b"not hdf5").unwrap();
        let e = read(&p).unwrap_err().to_string();
        assert!(e.contains("t.h5: opening it as HDF5"), "{e}");
    }
}
