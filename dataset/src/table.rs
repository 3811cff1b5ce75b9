//! The index on disk: a directory of Parquet parts, `part-<I>-of-<N>.parquet` (one per shard
//! of `labrig dataset index --shard I/N`; together they are the index), or the merged index
//! `labrig dataset merge` makes of them (hive-partitioned: `source_format=<f>/part-*.parquet`,
//! that column in the folder name only), snappy-compressed, with
//! flat columns any Parquet reader (pyarrow, DuckDB, Spark) can query by name:
//!
//! `index_version, episode_id, source_path, source_format, file_size, file_mtime_ns, success,
//! lab, building, scene_id, instruction, instruction_2, instruction_3, length`, per camera
//! `<c>` of ext1, ext2, rs1, rs2, wrist: `<c>_serial, <c>_x, <c>_y, <c>_z, <c>_roll,
//! <c>_pitch, <c>_yaw, <c>_radius_m, <c>_polar_deg, <c>_azimuth_deg, <c>_bin,
//! <c>_extrinsics_from` (`metadata` or `recalibrated`), then
//! `object_x, object_y, object_z, object, primitive, colour, sim_dv`.

use crate::INDEX_VERSION;
use crate::row::{CAMERAS, CameraRow, IndexRow};
use arrow_array::cast::AsArray;
use arrow_array::types::{Float64Type, Int64Type, UInt32Type, UInt64Type};
use arrow_array::{
    ArrayRef, BooleanArray, Float64Array, Int64Array, RecordBatch, StringArray, UInt32Array, UInt64Array,
};
use arrow_schema::{DataType, Field, Schema};
use parquet::arrow::ArrowWriter;
use parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder;
use parquet::basic::Compression;
use parquet::file::properties::WriterProperties;
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::sync::Arc;

#[derive(Debug, thiserror::Error)]
pub enum TableError {
    #[error("{path}: {error}")]
    Io { path: String, error: std::io::Error },
    #[error("{path}: {error}")]
    Parquet { path: String, error: parquet::errors::ParquetError },
    #[error("{path}: column `{column}` {what}")]
    Column { path: String, column: String, what: String },
    #[error("{path}: index version {found}, this labrig reads {INDEX_VERSION}: index the data again")]
    Version { path: String, found: u32 },
    #[error("{0}: no index parts (part-*.parquet) there")]
    Empty(String),
    #[error("{path}: {why}")]
    Incomplete { path: String, why: String },
}

/// The file of shard `i` of `n`.
pub fn part_name(i: usize, n: usize) -> String {
    format!("part-{i:05}-of-{n:05}.parquet")
}

fn columns(rows: &[IndexRow], with_format: bool) -> Vec<(Field, ArrayRef)> {
    fn text(name: &str, rows: &[IndexRow], f: impl Fn(&IndexRow) -> Option<&str>) -> (Field, ArrayRef) {
        let a: StringArray = rows.iter().map(f).collect();
        (Field::new(name, DataType::Utf8, true), Arc::new(a))
    }
    fn float(name: &str, rows: &[IndexRow], f: impl Fn(&IndexRow) -> Option<f64>) -> (Field, ArrayRef) {
        let a: Float64Array = rows.iter().map(f).collect();
        (Field::new(name, DataType::Float64, true), Arc::new(a))
    }
    let mut c = vec![
        (
            Field::new("index_version", DataType::UInt32, false),
            Arc::new(rows.iter().map(|r| r.index_version).collect::<UInt32Array>()) as ArrayRef,
        ),
        text("episode_id", rows, |r| Some(&r.episode_id)),
        text("source_path", rows, |r| Some(&r.source_path)),
        (
            Field::new("file_size", DataType::UInt64, false),
            Arc::new(rows.iter().map(|r| r.file_size).collect::<UInt64Array>()),
        ),
        (
            Field::new("file_mtime_ns", DataType::Int64, false),
            Arc::new(rows.iter().map(|r| r.file_mtime_ns).collect::<Int64Array>()),
        ),
        (
            Field::new("success", DataType::Boolean, true),
            Arc::new(rows.iter().map(|r| r.success).collect::<BooleanArray>()),
        ),
        text("lab", rows, |r| Some(&r.lab)),
        text("building", rows, |r| Some(&r.building)),
        text("scene_id", rows, |r| Some(&r.scene_id)),
        text("instruction", rows, |r| r.instruction.as_deref()),
        text("instruction_2", rows, |r| r.instruction_2.as_deref()),
        text("instruction_3", rows, |r| r.instruction_3.as_deref()),
        (
            Field::new("length", DataType::UInt64, false),
            Arc::new(rows.iter().map(|r| r.length).collect::<UInt64Array>()),
        ),
    ];
    if with_format {
        c.insert(3, text("source_format", rows, |r| Some(&r.source_format)));
    }
    for (k, cam) in CAMERAS.iter().enumerate() {
        let at = |r: &IndexRow| r.cameras.get(k).cloned().unwrap_or_default();
        c.push(text(&format!("{cam}_serial"), rows, |r| r.cameras.get(k).and_then(|c| c.serial.as_deref())));
        for (i, axis) in ["x", "y", "z"].iter().enumerate() {
            c.push(float(&format!("{cam}_{axis}"), rows, |r| at(r).position.map(|p| p[i])));
        }
        for (i, axis) in ["roll", "pitch", "yaw"].iter().enumerate() {
            c.push(float(&format!("{cam}_{axis}"), rows, |r| at(r).euler.map(|e| e[i])));
        }
        c.push(float(&format!("{cam}_radius_m"), rows, |r| at(r).radius_m));
        c.push(float(&format!("{cam}_polar_deg"), rows, |r| at(r).polar_deg));
        c.push(float(&format!("{cam}_azimuth_deg"), rows, |r| at(r).azimuth_deg));
        c.push(text(&format!("{cam}_bin"), rows, |r| r.cameras.get(k).and_then(|c| c.bin.as_deref())));
        c.push(text(&format!("{cam}_extrinsics_from"), rows, |r| {
            r.cameras.get(k).and_then(|c| c.extrinsics_from.as_deref())
        }));
    }
    for (i, axis) in ["x", "y", "z"].iter().enumerate() {
        c.push(float(&format!("object_{axis}"), rows, |r| r.object_position.map(|p| p[i])));
    }
    c.push(text("object", rows, |r| r.object.as_deref()));
    c.push(text("primitive", rows, |r| r.primitive.as_deref()));
    c.push(text("colour", rows, |r| r.colour.as_deref()));
    c.push(text("sim_dv", rows, |r| r.sim_dv.as_deref()));
    c
}

/// Writes `rows` as one Parquet file (through a temporary name, so a reader never sees half).
/// `recalibration` is the stamp of the `--extrinsics` file the rows were made with ("" for none).
pub fn write_part(path: &Path, rows: &[IndexRow], recalibration: &str) -> Result<(), TableError> {
    write(path, rows, recalibration, true)
}

fn write(path: &Path, rows: &[IndexRow], recalibration: &str, with_format: bool) -> Result<(), TableError> {
    let pq = |error| TableError::Parquet { path: path.display().to_string(), error };
    let io = |error| TableError::Io { path: path.display().to_string(), error };
    let (fields, arrays): (Vec<Field>, Vec<ArrayRef>) = columns(rows, with_format).into_iter().unzip();
    let schema = Arc::new(Schema::new(fields));
    let batch = RecordBatch::try_new(schema.clone(), arrays).map_err(|e| pq(e.into()))?;
    let tmp = path.with_extension("parquet.tmp");
    let file = std::fs::File::create(&tmp).map_err(io)?;
    let props = WriterProperties::builder()
        .set_compression(Compression::SNAPPY)
        .set_key_value_metadata(Some(vec![
            parquet::file::metadata::KeyValue::new("labrig_index_version".into(), INDEX_VERSION.to_string()),
            parquet::file::metadata::KeyValue::new(RECALIBRATION_KEY.into(), recalibration.to_owned()),
        ]))
        .build();
    let mut w = ArrowWriter::try_new(file, schema, Some(props)).map_err(pq)?;
    w.write(&batch).map_err(pq)?;
    w.close().map_err(pq)?;
    std::fs::rename(&tmp, path).map_err(io)
}

const RECALIBRATION_KEY: &str = "labrig_extrinsics_override";

/// The stamp of the `--extrinsics` file a part was made with ("" for none; None when unreadable).
pub fn part_recalibration(path: &Path) -> Option<String> {
    let file = std::fs::File::open(path).ok()?;
    let b = ParquetRecordBatchReaderBuilder::try_new(file).ok()?;
    let kv = b.metadata().file_metadata().key_value_metadata()?;
    Some(kv.iter().find(|k| k.key == RECALIBRATION_KEY).and_then(|k| k.value.clone()).unwrap_or_default())
}

/// Reads one part.
pub fn read_part(path: &Path) -> Result<Vec<IndexRow>, TableError> {
    let p = path.display().to_string();
    let pq = |error| TableError::Parquet { path: p.clone(), error };
    let file = std::fs::File::open(path).map_err(|error| TableError::Io { path: p.clone(), error })?;
    let reader = ParquetRecordBatchReaderBuilder::try_new(file).map_err(pq)?.build().map_err(pq)?;
    let mut rows = Vec::new();
    for batch in reader {
        let batch = batch.map_err(|e| pq(e.into()))?;
        rows.extend(rows_of(&p, &batch)?);
    }
    Ok(rows)
}

fn rows_of(path: &str, b: &RecordBatch) -> Result<Vec<IndexRow>, TableError> {
    let col = |name: &str| {
        b.column_by_name(name).ok_or_else(|| TableError::Column {
            path: path.to_owned(),
            column: name.to_owned(),
            what: "is missing".into(),
        })
    };
    let wrong = |name: &str| TableError::Column {
        path: path.to_owned(),
        column: name.to_owned(),
        what: "has another type".into(),
    };
    let text = |name: &str| -> Result<Vec<Option<String>>, TableError> {
        let a = col(name)?.as_string_opt::<i32>().ok_or_else(|| wrong(name))?;
        Ok(a.iter().map(|v| v.map(str::to_owned)).collect())
    };
    let float = |name: &str| -> Result<Vec<Option<f64>>, TableError> {
        Ok(col(name)?.as_primitive_opt::<Float64Type>().ok_or_else(|| wrong(name))?.iter().collect())
    };
    let version: Vec<Option<u32>> =
        col("index_version")?.as_primitive_opt::<UInt32Type>().ok_or_else(|| wrong("index_version"))?.iter().collect();
    if let Some(Some(v)) = version.iter().find(|v| **v != Some(INDEX_VERSION)) {
        return Err(TableError::Version { path: path.to_owned(), found: *v });
    }
    let u64s = |name: &str| -> Result<Vec<Option<u64>>, TableError> {
        Ok(col(name)?.as_primitive_opt::<UInt64Type>().ok_or_else(|| wrong(name))?.iter().collect())
    };
    let id = text("episode_id")?;
    let source = text("source_path")?;
    // A merged index's files leave the partition key to their folder's name (hive style).
    let format = match b.column_by_name("source_format") {
        Some(_) => text("source_format")?,
        None => {
            let key = Path::new(path)
                .parent()
                .and_then(|d| d.file_name())
                .and_then(|n| n.to_str())
                .and_then(|n| n.strip_prefix(PARTITION_KEY))
                .and_then(|n| n.strip_prefix('='))
                .ok_or_else(|| TableError::Column {
                    path: path.to_owned(),
                    column: "source_format".into(),
                    what: format!("is missing, and the file is in no `{PARTITION_KEY}=<f>` folder"),
                })?;
            vec![Some(key.to_owned()); b.num_rows()]
        }
    };
    let size = u64s("file_size")?;
    let mtime: Vec<Option<i64>> =
        col("file_mtime_ns")?.as_primitive_opt::<Int64Type>().ok_or_else(|| wrong("file_mtime_ns"))?.iter().collect();
    let success: Vec<Option<bool>> = col("success")?.as_boolean_opt().ok_or_else(|| wrong("success"))?.iter().collect();
    let (lab, building, scene) = (text("lab")?, text("building")?, text("scene_id")?);
    let (i1, i2, i3) = (text("instruction")?, text("instruction_2")?, text("instruction_3")?);
    let length = u64s("length")?;
    let mut cams = Vec::new();
    for cam in CAMERAS {
        let f = |s: &str| float(&format!("{cam}_{s}"));
        cams.push((
            text(&format!("{cam}_serial"))?,
            [f("x")?, f("y")?, f("z")?],
            [f("roll")?, f("pitch")?, f("yaw")?],
            [f("radius_m")?, f("polar_deg")?, f("azimuth_deg")?],
            text(&format!("{cam}_bin"))?,
            text(&format!("{cam}_extrinsics_from"))?,
        ));
    }
    let obj = [float("object_x")?, float("object_y")?, float("object_z")?];
    let (object, primitive, colour, sim) = (text("object")?, text("primitive")?, text("colour")?, text("sim_dv")?);
    let three = |v: &[Vec<Option<f64>>; 3], i: usize| Some([v[0][i]?, v[1][i]?, v[2][i]?]);
    Ok((0..b.num_rows())
        .map(|i| IndexRow {
            index_version: INDEX_VERSION,
            episode_id: id[i].clone().unwrap_or_default(),
            source_path: source[i].clone().unwrap_or_default(),
            source_format: format[i].clone().unwrap_or_default(),
            file_size: size[i].unwrap_or(0),
            file_mtime_ns: mtime[i].unwrap_or(0),
            success: success[i],
            lab: lab[i].clone().unwrap_or_default(),
            building: building[i].clone().unwrap_or_default(),
            scene_id: scene[i].clone().unwrap_or_default(),
            instruction: i1[i].clone(),
            instruction_2: i2[i].clone(),
            instruction_3: i3[i].clone(),
            length: length[i].unwrap_or(0),
            cameras: cams
                .iter()
                .map(|(serial, pos, eul, sph, bin, from)| CameraRow {
                    serial: serial[i].clone(),
                    position: three(pos, i),
                    euler: three(eul, i),
                    radius_m: sph[0][i],
                    polar_deg: sph[1][i],
                    azimuth_deg: sph[2][i],
                    bin: bin[i].clone(),
                    extrinsics_from: from[i].clone(),
                })
                .collect(),
            object_position: three(&obj, i),
            object: object[i].clone(),
            primitive: primitive[i].clone(),
            colour: colour[i].clone(),
            sim_dv: sim[i].clone(),
        })
        .collect())
}

/// The shard of a part's file name: `part-00003-of-00016.parquet` is shard 3 of 16.
pub fn shard_of_name(path: &Path) -> Option<(usize, usize)> {
    let n = path.file_name()?.to_str()?.strip_prefix("part-")?.strip_suffix(".parquet")?;
    let (i, n) = n.split_once("-of-")?;
    Some((i.parse().ok()?, n.parse().ok()?))
}

/// The directory a merged index keeps `source_format`'s rows in (hive partitioning).
pub const PARTITION_KEY: &str = "source_format";

fn part_files(dir: &Path) -> Result<Vec<PathBuf>, TableError> {
    let io = |error| TableError::Io { path: dir.display().to_string(), error };
    let mut parts: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(io)?
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|p| {
            let n = p.file_name().and_then(|n| n.to_str()).unwrap_or("");
            n.starts_with("part-") && n.ends_with(".parquet")
        })
        .collect();
    parts.sort();
    Ok(parts)
}

/// The partitions of a merged index (`source_format=<f>` folders), sorted.
fn partitions(dir: &Path) -> Result<Vec<PathBuf>, TableError> {
    let io = |error| TableError::Io { path: dir.display().to_string(), error };
    let prefix = format!("{PARTITION_KEY}=");
    let mut p: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(io)?
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|p| p.is_dir() && p.file_name().and_then(|n| n.to_str()).is_some_and(|n| n.starts_with(&prefix)))
        .collect();
    p.sort();
    Ok(p)
}

/// The parts of an index directory, sorted: `labrig dataset index`'s shards
/// (`part-<I>-of-<N>.parquet`), or a merged index's partitions (`source_format=<f>/part-*`).
pub fn parts(dir: &Path) -> Result<Vec<PathBuf>, TableError> {
    let flat = part_files(dir)?;
    if !flat.is_empty() {
        return Ok(flat);
    }
    let mut parts = Vec::new();
    for p in partitions(dir)? {
        parts.extend(part_files(&p)?);
    }
    Ok(parts)
}

/// Why a directory of shard parts is not one whole index.
pub fn incomplete(parts: &[PathBuf]) -> Option<String> {
    let shards: Vec<(usize, usize)> = parts.iter().filter_map(|p| shard_of_name(p)).collect();
    let counts: BTreeSet<usize> = shards.iter().map(|s| s.1).collect();
    if counts.len() > 1 {
        let names: Vec<String> = counts.iter().map(|n| format!("of {n}")).collect();
        return Some(format!(
            "parts of {} shardings ({}): delete the stale parts, or index again with one --shard N",
            counts.len(),
            names.join(", ")
        ));
    }
    let n = *counts.first()?;
    let have: BTreeSet<usize> = shards.iter().map(|s| s.0).collect();
    let missing: Vec<String> = (0..n).filter(|i| !have.contains(i)).map(|i| format!("{i}/{n}")).collect();
    (!missing.is_empty()).then(|| format!("shards {} missing (of {n})", missing.join(", ")))
}

/// Every row of an index directory (all its parts). Shard parts must form one whole set.
pub fn read_index(dir: &Path) -> Result<Vec<IndexRow>, TableError> {
    let parts = parts(dir)?;
    if parts.is_empty() {
        return Err(TableError::Empty(dir.display().to_string()));
    }
    if parts.iter().all(|p| p.parent() == Some(dir))
        && let Some(why) = incomplete(&parts)
    {
        return Err(TableError::Incomplete { path: dir.display().to_string(), why });
    }
    let mut rows = Vec::new();
    for p in parts {
        rows.extend(read_part(&p)?);
    }
    Ok(rows)
}

/// What `merge` wrote (also `_index.json` in the merged index).
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize, PartialEq)]
pub struct Merged {
    pub index_version: u32,
    pub rows: usize,
    pub shards: usize,
    pub by_format: BTreeMap<String, usize>,
    /// The `--extrinsics` stamp every part was made with ("" for none).
    pub extrinsics_override: String,
    pub files: Vec<PathBuf>,
}

/// The file a merged index describes itself in.
pub const MERGED_FILE: &str = "_index.json";

/// Merges the shard parts in `parts_dir` (one whole set) into `out`, hive-partitioned by
/// source format: `<out>/source_format=<f>/part-00000-of-00001.parquet` (the column itself left
/// to the folder name, as hive readers expect: pyarrow refuses a key that is also a column),
/// rows sorted by source path, plus `_index.json`. Partitions of an earlier merge that no longer have rows are removed.
pub fn merge(parts_dir: &Path, out: &Path) -> Result<Merged, TableError> {
    let parts = part_files(parts_dir)?;
    if parts.is_empty() {
        return Err(TableError::Empty(parts_dir.display().to_string()));
    }
    let dir = parts_dir.display().to_string();
    if let Some(why) = incomplete(&parts) {
        return Err(TableError::Incomplete { path: dir, why });
    }
    let stamps: BTreeSet<String> = parts.iter().map(|p| part_recalibration(p).unwrap_or_default()).collect();
    if stamps.len() > 1 {
        return Err(TableError::Incomplete {
            path: dir,
            why: "its parts were indexed with different --extrinsics files: index every shard with the same one".into(),
        });
    }
    let mut rows = Vec::new();
    for p in &parts {
        rows.extend(read_part(p)?);
    }
    rows.sort_by(|a, b| a.source_path.cmp(&b.source_path));
    if let Some(w) = rows.windows(2).find(|w| w[0].source_path == w[1].source_path) {
        return Err(TableError::Incomplete {
            path: dir,
            why: format!("{} is in more than one part: the parts overlap", w[0].source_path),
        });
    }
    let io = |p: &Path, error| TableError::Io { path: p.display().to_string(), error };
    std::fs::create_dir_all(out).map_err(|e| io(out, e))?;
    let stamp = stamps.into_iter().next().unwrap_or_default();
    let mut by_format: BTreeMap<String, Vec<IndexRow>> = BTreeMap::new();
    for r in rows {
        by_format.entry(r.source_format.clone()).or_default().push(r);
    }
    let mut files = Vec::new();
    for (format, rows) in &by_format {
        let p = out.join(format!("{PARTITION_KEY}={format}"));
        std::fs::create_dir_all(&p).map_err(|e| io(&p, e))?;
        let file = p.join(part_name(0, 1));
        write(&file, rows, &stamp, false)?;
        files.push(file);
    }
    for p in partitions(out)? {
        let format = p.file_name().and_then(|n| n.to_str()).unwrap_or("")[PARTITION_KEY.len() + 1..].to_owned();
        if !by_format.contains_key(&format) {
            std::fs::remove_dir_all(&p).map_err(|e| io(&p, e))?;
        }
    }
    let merged = Merged {
        index_version: INDEX_VERSION,
        rows: by_format.values().map(Vec::len).sum(),
        shards: parts.len(),
        by_format: by_format.iter().map(|(f, r)| (f.clone(), r.len())).collect(),
        extrinsics_override: stamp,
        files,
    };
    let json = out.join(MERGED_FILE);
    std::fs::write(&json, serde_json::to_string_pretty(&merged).expect("plain data") + "\n")
        .map_err(|e| io(&json, e))?;
    Ok(merged)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample(i: usize) -> IndexRow {
        let mut cameras: Vec<CameraRow> = CAMERAS.iter().map(|_| CameraRow::default()).collect();
        cameras[0] =
            crate::dv::camera_row(Some("239".into()), Some([0.1 * i as f64, 0.5, 0.6, 0.1, 0.2, 0.3]), [0.5, 0.0, 0.0]);
        IndexRow {
            index_version: INDEX_VERSION,
            episode_id: format!("LAB+op+{i}"),
            source_path: format!("/data/{i}"),
            source_format: "droid_raw".into(),
            file_size: 1000 + i as u64,
            file_mtime_ns: 7,
            success: if i.is_multiple_of(3) { None } else { Some(i.is_multiple_of(2)) },
            lab: "LAB".into(),
            instruction: Some("put the red cube in the bin".into()),
            length: 120,
            cameras,
            object_position: i.is_multiple_of(2).then_some([0.5, 0.1, 0.05]),
            object: Some("cube".into()),
            primitive: Some("place".into()),
            colour: Some("red".into()),
            ..IndexRow::default()
        }
    }

    #[test]
    fn rows_survive_a_parquet_round_trip_with_their_nulls() {
        let dir = tempfile::tempdir().unwrap();
        let rows: Vec<IndexRow> = (0..7).map(sample).collect();
        let path = dir.path().join(part_name(0, 1));
        write_part(&path, &rows, "").unwrap();
        assert_eq!(read_index(dir.path()).unwrap(), rows);
    }

    #[test]
    fn shards_merge_into_a_hive_partitioned_index_only_when_whole() {
        let dir = tempfile::tempdir().unwrap();
        let (parts, out) = (dir.path().join("parts"), dir.path().join("index"));
        std::fs::create_dir_all(&parts).unwrap();
        let mut rows: Vec<IndexRow> = (0..9).map(sample).collect();
        for r in rows.iter_mut().skip(6) {
            r.source_format = "rlds".into();
        }
        for i in 0..3 {
            let mine: Vec<IndexRow> = rows.iter().skip(i).step_by(3).cloned().collect();
            write_part(&parts.join(part_name(i, 3)), &mine, "").unwrap();
        }
        // A stale part of another sharding is named, not read twice.
        write_part(&parts.join(part_name(0, 1)), &rows, "").unwrap();
        let e = merge(&parts, &out).unwrap_err().to_string();
        assert!(e.contains("2 shardings"), "{e}");
        assert!(read_index(&parts).unwrap_err().to_string().contains("2 shardings"));
        std::fs::remove_file(parts.join(part_name(0, 1))).unwrap();
        std::fs::rename(parts.join(part_name(1, 3)), dir.path().join("away")).unwrap();
        let e = merge(&parts, &out).unwrap_err().to_string();
        assert!(e.contains("shards 1/3 missing"), "{e}");
        std::fs::rename(dir.path().join("away"), parts.join(part_name(1, 3))).unwrap();
        let m = merge(&parts, &out).unwrap();
        assert_eq!((m.rows, m.shards), (9, 3));
        assert_eq!(m.by_format, BTreeMap::from([("droid_raw".into(), 6), ("rlds".into(), 3)]));
        assert!(out.join("source_format=rlds").join(part_name(0, 1)).is_file());
        let mut back = read_index(&out).unwrap();
        back.sort_by(|a, b| a.source_path.cmp(&b.source_path));
        rows.sort_by(|a, b| a.source_path.cmp(&b.source_path));
        assert_eq!(back, rows);
        // A partition whose rows are gone goes too.
        for i in 0..3 {
            let mine: Vec<IndexRow> = rows.iter().take(6).skip(i).step_by(3).cloned().collect();
            write_part(&parts.join(part_name(i, 3)), &mine, "").unwrap();
        }
        assert_eq!(merge(&parts, &out).unwrap().rows, 6);
        assert!(!out.join("source_format=rlds").exists());
    }
}
