//! DROID's RLDS release: TFDS TFRecord shards (`droid_101-train.tfrecord-00000-of-02048`),
//! one `tf.train.Example` per episode with the steps' features flattened step after step
//! (`steps/observation/cartesian_position` holds T x 6 floats). Read here without TensorFlow
//! and without touching image bytes: the records' framing (length, masked CRC-32C of the length,
//! data, masked CRC-32C of the data) is checked, and the Example's feature map is walked,
//! keeping only the wanted keys' values (an image's bytes are skipped by their length).

use std::collections::BTreeMap;

/// A feature's values.
#[derive(Debug, Clone, PartialEq)]
pub enum Values {
    Bytes(Vec<Vec<u8>>),
    Floats(Vec<f32>),
    Ints(Vec<i64>),
}

/// Why a TFRecord file or a `tf.train.Example` in it cannot be read.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum RldsError {
    #[error("record {record} at byte {at}: truncated header")]
    TruncatedHeader { record: usize, at: usize },
    #[error("record {record} at byte {at}: the length's CRC does not match (not a TFRecord file?)")]
    LengthCrc { record: usize, at: usize },
    #[error("record {record} at byte {at}: {len} bytes announced, the file ends first")]
    TruncatedData { record: usize, at: usize, len: usize },
    #[error("record {record}: truncated CRC")]
    TruncatedCrc { record: usize },
    #[error("record {record} at byte {at}: the data's CRC does not match (damaged)")]
    DataCrc { record: usize, at: usize },
    #[error("protobuf: truncated varint")]
    TruncatedVarint,
    #[error("protobuf: varint too long")]
    VarintTooLong,
    #[error("protobuf: truncated fixed field")]
    TruncatedFixed,
    #[error("protobuf: truncated length-delimited field")]
    TruncatedLen,
    #[error("protobuf: wire type {0} not expected in tf.train.Example")]
    WireType(u8),
    #[error("float_list: bad wire type")]
    FloatListWire,
    #[error("int64_list: bad wire type")]
    Int64ListWire,
}

/// CRC-32C (Castagnoli), as TFRecord frames use it.
fn crc32c(data: &[u8]) -> u32 {
    static TABLE: std::sync::OnceLock<[u32; 256]> = std::sync::OnceLock::new();
    let table = TABLE.get_or_init(|| {
        let mut t = [0u32; 256];
        for (i, e) in t.iter_mut().enumerate() {
            let mut c = i as u32;
            for _ in 0..8 {
                c = if c & 1 != 0 { 0x82F6_3B78 ^ (c >> 1) } else { c >> 1 };
            }
            *e = c;
        }
        t
    });
    !data.iter().fold(!0u32, |c, &b| table[((c ^ b as u32) & 0xff) as usize] ^ (c >> 8))
}

fn masked(crc: u32) -> u32 {
    (crc.rotate_right(15)).wrapping_add(0xa282_ead8)
}

/// The records of a TFRecord file, CRC-checked.
pub fn records(bytes: &[u8]) -> Result<Vec<&[u8]>, RldsError> {
    let mut out = Vec::new();
    let mut at = 0usize;
    while at < bytes.len() {
        let record = out.len();
        let head = bytes.get(at..at + 12).ok_or(RldsError::TruncatedHeader { record, at })?;
        let len = u64::from_le_bytes(head[..8].try_into().expect("8 bytes")) as usize;
        let crc = u32::from_le_bytes(head[8..12].try_into().expect("4 bytes"));
        if masked(crc32c(&head[..8])) != crc {
            return Err(RldsError::LengthCrc { record, at });
        }
        let data = bytes.get(at + 12..at + 12 + len).ok_or(RldsError::TruncatedData { record, at, len })?;
        let tail = bytes.get(at + 12 + len..at + 16 + len).ok_or(RldsError::TruncatedCrc { record })?;
        if masked(crc32c(data)) != u32::from_le_bytes(tail.try_into().expect("4 bytes")) {
            return Err(RldsError::DataCrc { record, at });
        }
        out.push(data);
        at += 16 + len;
    }
    Ok(out)
}

fn varint(b: &[u8], at: &mut usize) -> Result<u64, RldsError> {
    let mut v = 0u64;
    for shift in (0..64).step_by(7) {
        let byte = *b.get(*at).ok_or(RldsError::TruncatedVarint)?;
        *at += 1;
        v |= ((byte & 0x7f) as u64) << shift;
        if byte & 0x80 == 0 {
            return Ok(v);
        }
    }
    Err(RldsError::VarintTooLong)
}

/// A protobuf field: number, wire type, the payload of a LEN or fixed field, a varint's value.
type Field<'a> = (u64, u8, &'a [u8], u64);

/// The fields of a protobuf message, LEN payloads sliced (never copied).
fn fields(b: &[u8]) -> Result<Vec<Field<'_>>, RldsError> {
    let mut out = Vec::new();
    let mut at = 0;
    while at < b.len() {
        let key = varint(b, &mut at)?;
        let (field, wire) = (key >> 3, (key & 7) as u8);
        match wire {
            0 => {
                let v = varint(b, &mut at)?;
                out.push((field, wire, &b[0..0], v));
            }
            1 | 5 => {
                let n = if wire == 1 { 8 } else { 4 };
                let s = b.get(at..at + n).ok_or(RldsError::TruncatedFixed)?;
                at += n;
                out.push((field, wire, s, 0));
            }
            2 => {
                let len = varint(b, &mut at)? as usize;
                let s = b.get(at..at + len).ok_or(RldsError::TruncatedLen)?;
                at += len;
                out.push((field, wire, s, 0));
            }
            other => return Err(RldsError::WireType(other)),
        }
    }
    Ok(out)
}

/// Decodes a `Feature` (bytes_list = 1, float_list = 2, int64_list = 3; packed or not).
fn feature(b: &[u8]) -> Result<Values, RldsError> {
    let mut v = Values::Bytes(Vec::new());
    for (kind, _, list, _) in fields(b)? {
        v = match kind {
            1 => Values::Bytes(fields(list)?.into_iter().filter(|f| f.0 == 1).map(|f| f.2.to_vec()).collect()),
            2 => {
                let mut out = Vec::new();
                for (n, wire, s, _) in fields(list)? {
                    if n != 1 {
                        continue;
                    }
                    let chunk = if wire == 2 || wire == 5 { s } else { return Err(RldsError::FloatListWire) };
                    out.extend(chunk.chunks_exact(4).map(|c| f32::from_le_bytes(c.try_into().expect("4 bytes"))));
                }
                Values::Floats(out)
            }
            3 => {
                let mut out = Vec::new();
                for (n, wire, s, val) in fields(list)? {
                    if n != 1 {
                        continue;
                    }
                    match wire {
                        0 => out.push(val as i64),
                        2 => {
                            let mut at = 0;
                            while at < s.len() {
                                out.push(varint(s, &mut at)? as i64);
                            }
                        }
                        _ => return Err(RldsError::Int64ListWire),
                    }
                }
                Values::Ints(out)
            }
            _ => continue,
        };
    }
    Ok(v)
}

/// The `wanted` features of a serialized `tf.train.Example` (others, images included, are
/// skipped by their length, never copied).
pub fn example(b: &[u8], wanted: &[&str]) -> Result<BTreeMap<String, Values>, RldsError> {
    let mut out = BTreeMap::new();
    for (n, _, features, _) in fields(b)? {
        if n != 1 {
            continue;
        }
        for (m, _, entry, _) in fields(features)? {
            if m != 1 {
                continue;
            }
            let mut key: Option<&[u8]> = None;
            let mut value: Option<&[u8]> = None;
            for (k, _, s, _) in fields(entry)? {
                match k {
                    1 => key = Some(s),
                    2 => value = Some(s),
                    _ => {}
                }
            }
            let Some(key) = key.and_then(|k| std::str::from_utf8(k).ok()) else { continue };
            if wanted.contains(&key) {
                out.insert(key.to_owned(), feature(value.unwrap_or(&[]))?);
            }
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn crc32c_is_castagnolis() {
        // The check value of CRC-32C.
        assert_eq!(crc32c(b"123456789"), 0xE306_9283);
    }

    #[test]
    fn a_damaged_record_is_refused() {
        let data = b"hello";
        let len = (data.len() as u64).to_le_bytes();
        let mut f = len.to_vec();
        f.extend(masked(crc32c(&len)).to_le_bytes());
        f.extend(data);
        f.extend(masked(crc32c(data)).to_le_bytes());
        assert_eq!(records(&f).unwrap(), vec![&data[..]]);
        let mut bad = f.clone();
        bad[13] ^= 1;
        assert!(records(&bad).unwrap_err().to_string().contains("data's CRC"));
        assert!(records(&f[..f.len() - 2]).unwrap_err().to_string().contains("truncated CRC"));
    }
}
