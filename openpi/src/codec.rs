//! openpi's message encoding: msgpack, numpy arrays as maps.
//!
//! An array is the map `{b"__ndarray__": true, b"data": <raw bytes, C order>, b"dtype": "<f4",
//! b"shape": [..]}` and a numpy scalar `{b"__npgeneric__": true, b"data": <value>, b"dtype": ..}`;
//! those four keys are msgpack **bin**, the observation's own keys are str. The dtype is read
//! from each message (numpy's `dtype.str`: byte order, kind, size), never assumed.

pub use rmpv::Value;

/// A message that is not what openpi's protocol carries, named.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum CodecError {
    #[error("not msgpack: {0}")]
    Msgpack(String),
    #[error("{key}: {why}")]
    Field { key: String, why: String },
    #[error("{key}: {source}")]
    Dtype {
        key: String,
        #[source]
        source: DtypeError,
    },
}

/// A dtype string that is not one numpy writes for the arrays labrig reads.
#[derive(Debug, Clone, thiserror::Error, PartialEq, Eq)]
pub enum DtypeError {
    #[error("dtype {dtype:?} is not numpy's dtype.str")]
    NotDtypeStr { dtype: String },
    #[error("dtype {dtype:?}: no byte order")]
    NoByteOrder { dtype: String },
    #[error("dtype {dtype:?}: no size")]
    NoSize { dtype: String },
    #[error("dtype {dtype:?}: labrig reads bool, int, uint and float32/64 arrays")]
    Unsupported { dtype: String },
}

fn field(key: &str, why: impl Into<String>) -> CodecError {
    CodecError::Field { key: key.to_owned(), why: why.into() }
}

fn dtype_error(key: &str, source: DtypeError) -> CodecError {
    CodecError::Dtype { key: key.to_owned(), source }
}

/// The element types numpy sends that labrig reads (bool, ints, floats).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    Bool,
    Int,
    Uint,
    Float,
}

/// A numpy dtype as `dtype.str` writes it: `<f4`, `|u1`, `>i8`, ...
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Dtype {
    pub kind: Kind,
    pub size: usize,
    pub big_endian: bool,
}

impl Dtype {
    pub const F32: Dtype = Dtype { kind: Kind::Float, size: 4, big_endian: false };
    pub const F64: Dtype = Dtype { kind: Kind::Float, size: 8, big_endian: false };
    pub const U8: Dtype = Dtype { kind: Kind::Uint, size: 1, big_endian: false };

    pub fn parse(s: &str) -> Result<Dtype, DtypeError> {
        let dtype = || s.to_owned();
        let b = s.as_bytes();
        if b.len() < 3 {
            return Err(DtypeError::NotDtypeStr { dtype: dtype() });
        }
        let big_endian = match b[0] {
            b'<' | b'|' | b'=' => false,
            b'>' => true,
            _ => return Err(DtypeError::NoByteOrder { dtype: dtype() }),
        };
        let size: usize = s[2..].parse().map_err(|_| DtypeError::NoSize { dtype: dtype() })?;
        let kind = match (b[1], size) {
            (b'b', 1) => Kind::Bool,
            (b'i', 1 | 2 | 4 | 8) => Kind::Int,
            (b'u', 1 | 2 | 4 | 8) => Kind::Uint,
            (b'f', 4 | 8) => Kind::Float,
            _ => return Err(DtypeError::Unsupported { dtype: dtype() }),
        };
        Ok(Dtype { kind, size, big_endian })
    }

    /// numpy's `dtype.str` for it.
    pub fn str(&self) -> String {
        let order = if self.size == 1 {
            '|'
        } else if self.big_endian {
            '>'
        } else {
            '<'
        };
        let kind = match self.kind {
            Kind::Bool => 'b',
            Kind::Int => 'i',
            Kind::Uint => 'u',
            Kind::Float => 'f',
        };
        format!("{order}{kind}{}", self.size)
    }

    fn read(&self, bytes: &[u8]) -> f64 {
        let mut b = [0u8; 8];
        b[..self.size].copy_from_slice(bytes);
        if self.big_endian {
            b[..self.size].reverse();
        }
        match (self.kind, self.size) {
            (Kind::Bool, _) => f64::from(b[0] != 0),
            (Kind::Float, 4) => f64::from(f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            (Kind::Float, _) => f64::from_le_bytes(b),
            (Kind::Uint, _) => u64::from_le_bytes(b) as f64,
            (Kind::Int, n) => {
                // Sign-extend from n bytes.
                let shift = 64 - 8 * n as u32;
                ((i64::from_le_bytes(b) << shift) >> shift) as f64
            }
        }
    }
}

/// A numpy array as it travels.
#[derive(Debug, Clone, PartialEq)]
pub struct Array {
    pub dtype: Dtype,
    pub shape: Vec<usize>,
    /// C order, the dtype's byte order.
    pub data: Vec<u8>,
}

impl Array {
    pub fn f32(shape: &[usize], values: &[f32]) -> Array {
        assert_eq!(shape.iter().product::<usize>(), values.len(), "shape and values disagree");
        Array { dtype: Dtype::F32, shape: shape.to_vec(), data: values.iter().flat_map(|v| v.to_le_bytes()).collect() }
    }

    pub fn f64(shape: &[usize], values: &[f64]) -> Array {
        assert_eq!(shape.iter().product::<usize>(), values.len(), "shape and values disagree");
        Array { dtype: Dtype::F64, shape: shape.to_vec(), data: values.iter().flat_map(|v| v.to_le_bytes()).collect() }
    }

    pub fn u8(shape: &[usize], values: Vec<u8>) -> Array {
        assert_eq!(shape.iter().product::<usize>(), values.len(), "shape and values disagree");
        Array { dtype: Dtype::U8, shape: shape.to_vec(), data: values }
    }

    pub fn len(&self) -> usize {
        self.shape.iter().product()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Every element as f64 (C order).
    pub fn to_f64(&self) -> Vec<f64> {
        self.data.chunks_exact(self.dtype.size).map(|c| self.dtype.read(c)).collect()
    }

    pub fn to_value(&self) -> Value {
        Value::Map(vec![
            (Value::Binary(b"__ndarray__".to_vec()), Value::Boolean(true)),
            (Value::Binary(b"data".to_vec()), Value::Binary(self.data.clone())),
            (Value::Binary(b"dtype".to_vec()), Value::String(self.dtype.str().into())),
            (
                Value::Binary(b"shape".to_vec()),
                Value::Array(self.shape.iter().map(|&d| Value::from(d as u64)).collect()),
            ),
        ])
    }

    /// `key` names the field in errors.
    pub fn from_value(key: &str, v: &Value) -> Result<Array, CodecError> {
        if bin_get(v, "__ndarray__").is_none() {
            return Err(field(key, format!("not a numpy array (no b\"__ndarray__\"): {}", brief(v))));
        }
        let dtype = match bin_get(v, "dtype") {
            Some(Value::String(s)) => Dtype::parse(s.as_str().unwrap_or("")).map_err(|e| dtype_error(key, e))?,
            Some(Value::Binary(b)) => Dtype::parse(&String::from_utf8_lossy(b)).map_err(|e| dtype_error(key, e))?,
            _ => return Err(field(key, "array without a dtype")),
        };
        let shape = match bin_get(v, "shape") {
            Some(Value::Array(dims)) => dims
                .iter()
                .map(|d| d.as_u64().map(|d| d as usize).ok_or_else(|| field(key, format!("shape entry {d}"))))
                .collect::<Result<Vec<_>, _>>()?,
            _ => return Err(field(key, "array without a shape")),
        };
        let data = match bin_get(v, "data") {
            Some(Value::Binary(b)) => b.clone(),
            _ => return Err(field(key, "array without its data bytes")),
        };
        let want = shape.iter().product::<usize>() * dtype.size;
        if data.len() != want {
            return Err(field(
                key,
                format!("{} bytes for shape {shape:?} of {} (expected {want})", data.len(), dtype.str()),
            ));
        }
        Ok(Array { dtype, shape, data })
    }
}

/// A map entry by a bin key (the array markers).
fn bin_get<'a>(v: &'a Value, key: &str) -> Option<&'a Value> {
    v.as_map()?.iter().find(|(k, _)| matches!(k, Value::Binary(b) if b == key.as_bytes())).map(|(_, v)| v)
}

/// A map entry by a str key (the observation's and the result's own keys).
pub fn get<'a>(v: &'a Value, key: &str) -> Option<&'a Value> {
    v.as_map()?.iter().find(|(k, _)| k.as_str() == Some(key)).map(|(_, v)| v)
}

/// A map with str keys.
pub fn map<K: Into<String>>(entries: impl IntoIterator<Item = (K, Value)>) -> Value {
    Value::Map(entries.into_iter().map(|(k, v)| (Value::String(k.into().into()), v)).collect())
}

/// Sets (or adds) a str-keyed entry of a map.
pub fn set(m: &mut Value, key: &str, value: Value) {
    if let Value::Map(entries) = m {
        match entries.iter_mut().find(|(k, _)| k.as_str() == Some(key)) {
            Some(e) => e.1 = value,
            None => entries.push((Value::String(key.into()), value)),
        }
    }
}

/// `key` of a map as an array (or a plain number / list of numbers, as a 0-d / 1-d array of
/// f64), its values as f64 with its shape.
pub fn numbers(m: &Value, key: &str) -> Result<(Vec<usize>, Vec<f64>), CodecError> {
    let v = get(m, key).ok_or_else(|| field(key, "missing"))?;
    number_array(key, v)
}

fn number_array(key: &str, v: &Value) -> Result<(Vec<usize>, Vec<f64>), CodecError> {
    if bin_get(v, "__ndarray__").is_some() {
        let a = Array::from_value(key, v)?;
        return Ok((a.shape.clone(), a.to_f64()));
    }
    if bin_get(v, "__npgeneric__").is_some() {
        let x = bin_get(v, "data").and_then(as_number).ok_or_else(|| field(key, "a numpy scalar without a number"))?;
        return Ok((vec![], vec![x]));
    }
    if let Some(x) = as_number(v) {
        return Ok((vec![], vec![x]));
    }
    if let Some(items) = v.as_array() {
        let xs = items.iter().map(as_number).collect::<Option<Vec<f64>>>();
        if let Some(xs) = xs {
            return Ok((vec![xs.len()], xs));
        }
    }
    Err(field(key, format!("not a number or an array of numbers: {}", brief(v))))
}

fn as_number(v: &Value) -> Option<f64> {
    match v {
        Value::F32(x) => Some(f64::from(*x)),
        Value::F64(x) => Some(*x),
        Value::Integer(i) => i.as_f64(),
        Value::Boolean(b) => Some(f64::from(u8::from(*b))),
        _ => None,
    }
}

/// A short description of a value for an error message.
pub fn brief(v: &Value) -> String {
    let s = match v {
        Value::Binary(b) => format!("{} bytes", b.len()),
        other => other.to_string(),
    };
    if s.len() > 120 { format!("{}...", &s[..s.floor_char_boundary(120)]) } else { s }
}

pub fn pack(v: &Value) -> Vec<u8> {
    let mut out = Vec::new();
    rmpv::encode::write_value(&mut out, v).expect("writing to a Vec cannot fail");
    out
}

pub fn unpack(bytes: &[u8]) -> Result<Value, CodecError> {
    let mut r = bytes;
    let v = rmpv::decode::read_value(&mut r).map_err(|e| CodecError::Msgpack(e.to_string()))?;
    if !r.is_empty() {
        return Err(CodecError::Msgpack(format!("{} bytes after the message", r.len())));
    }
    Ok(v)
}

/// A value as JSON text (arrays by dtype and shape): for ids and logs.
pub fn to_json_text(v: &Value) -> String {
    fn walk(v: &Value, out: &mut String) {
        if bin_get(v, "__ndarray__").is_some() {
            match Array::from_value("", v) {
                Ok(a) => out.push_str(&format!("\"ndarray {} {:?}\"", a.dtype.str(), a.shape)),
                Err(_) => out.push_str("\"ndarray\""),
            }
            return;
        }
        match v {
            Value::Map(entries) => {
                out.push('{');
                for (i, (k, v)) in entries.iter().enumerate() {
                    if i > 0 {
                        out.push(',');
                    }
                    let key = match k {
                        Value::String(s) => s.as_str().unwrap_or("?").to_owned(),
                        Value::Binary(b) => String::from_utf8_lossy(b).into_owned(),
                        other => other.to_string(),
                    };
                    out.push_str(&format!("{key:?}:"));
                    walk(v, out);
                }
                out.push('}');
            }
            Value::Array(items) => {
                out.push('[');
                for (i, v) in items.iter().enumerate() {
                    if i > 0 {
                        out.push(',');
                    }
                    walk(v, out);
                }
                out.push(']');
            }
            Value::String(s) => out.push_str(&format!("{:?}", s.as_str().unwrap_or(""))),
            Value::Nil => out.push_str("null"),
            Value::Binary(b) => out.push_str(&format!("\"{} bytes\"", b.len())),
            other => out.push_str(&other.to_string()),
        }
    }
    let mut s = String::new();
    walk(v, &mut s);
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn arrays_round_trip_with_bin_marker_keys() {
        let a = Array::f32(&[2, 3], &[1.0, -2.5, 3.0, 4.0, 5.0, 6.0]);
        let bytes = pack(&map([("actions", a.to_value())]));
        let back = unpack(&bytes).unwrap();
        let v = get(&back, "actions").unwrap();
        // The marker keys are bin, not str.
        assert!(v.as_map().unwrap().iter().all(|(k, _)| matches!(k, Value::Binary(_))));
        assert_eq!(Array::from_value("actions", v).unwrap(), a);
        assert_eq!(numbers(&back, "actions").unwrap(), (vec![2, 3], vec![1.0, -2.5, 3.0, 4.0, 5.0, 6.0]));
    }

    #[test]
    fn dtypes_are_read_from_the_message() {
        for (s, bytes, want) in [
            ("<f8", 1.5f64.to_le_bytes().to_vec(), 1.5),
            (">f4", 1.5f32.to_be_bytes().to_vec(), 1.5),
            ("|u1", vec![200], 200.0),
            ("|i1", vec![0xff], -1.0),
            ("<i4", (-7i32).to_le_bytes().to_vec(), -7.0),
            ("<i8", (-7i64).to_le_bytes().to_vec(), -7.0),
            ("|b1", vec![1], 1.0),
        ] {
            let d = Dtype::parse(s).unwrap();
            assert_eq!(d.str(), s.replace('=', "<"));
            let a = Array { dtype: d, shape: vec![1], data: bytes };
            assert_eq!(a.to_f64(), vec![want], "{s}");
        }
        assert!(Dtype::parse("<c16").unwrap_err().to_string().contains("labrig reads"));
        assert!(Dtype::parse("O").is_err());
    }

    #[test]
    fn a_malformed_array_is_named() {
        let mut v = Array::f32(&[4], &[0.0; 4]).to_value();
        if let Value::Map(e) = &mut v {
            e[3].1 = Value::Array(vec![Value::from(5u64)]);
        }
        let e = Array::from_value("observation/joint_position", &v).unwrap_err();
        assert_eq!(e.to_string(), "observation/joint_position: 16 bytes for shape [5] of <f4 (expected 20)");
        assert!(unpack(&[0x92, 0x01]).is_err(), "a truncated array");
        assert!(unpack(&[0x01, 0x02]).unwrap_err().to_string().contains("1 bytes after"));
        let e = numbers(&map([("a", Value::from("x"))]), "a").unwrap_err();
        assert!(e.to_string().starts_with("a: not a number"), "{e}");
        assert_eq!(numbers(&map([("a", Value::from(1))]), "b").unwrap_err().to_string(), "b: missing");
    }

    #[test]
    fn plain_numbers_and_numpy_scalars_read_as_arrays() {
        let scalar = Value::Map(vec![
            (Value::Binary(b"__npgeneric__".to_vec()), Value::Boolean(true)),
            (Value::Binary(b"data".to_vec()), Value::F64(0.25)),
            (Value::Binary(b"dtype".to_vec()), Value::from("<f8")),
        ]);
        let m = map([("s", scalar), ("l", Value::Array(vec![Value::from(1), Value::F64(2.5)]))]);
        assert_eq!(numbers(&m, "s").unwrap(), (vec![], vec![0.25]));
        assert_eq!(numbers(&m, "l").unwrap(), (vec![2], vec![1.0, 2.5]));
    }
}
