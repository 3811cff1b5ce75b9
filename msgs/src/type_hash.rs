//! ROS 2 type hashes (REP 2011, `RIHS01_<sha256 hex>`), computed from a type's `.msg` text as
//! rosidl computes them: each type's fields (name; type id, array capacity, string bound and
//! nested type name) as a `TypeDescription`, the type's own first and every type it refers to
//! after it (sorted by name), written as JSON with `", "` and `": "` separators and no default
//! values, then hashed. Comments and constants are not part of it.
//!
//! Since Iron, rmw implementations announce these in discovery (an endpoint's USER_DATA holds
//! `typehash=RIHS01_...;`), and ROS 2 tools compare them between peers.

use crate::RosMessage;
use sha2::{Digest, Sha256};

/// A `.msg` line that is not a field, a constant, a comment or blank.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{type_name}: line {line} `{text}`: {reason}")]
pub struct MsgSyntaxError {
    pub type_name: String,
    pub line: usize,
    pub text: String,
    pub reason: String,
}

/// One field as `type_description_interfaces/msg/FieldType` holds it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FieldType {
    pub type_id: u8,
    pub capacity: u64,
    pub string_capacity: u64,
    /// `pkg/msg/Name` for a nested type, else empty.
    pub nested_type_name: String,
}

/// One field: its name and type.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Field {
    pub name: String,
    pub ty: FieldType,
}

// type_description_interfaces/msg/FieldType: the element type ids, and what an array (+48),
// a bounded sequence (+96) and an unbounded sequence (+144) add to them.
const NESTED: u8 = 1;
const STRING: u8 = 17;
const WSTRING: u8 = 18;
const BOUNDED_STRING: u8 = 21;
const BOUNDED_WSTRING: u8 = 22;
const ARRAY: u8 = 48;
const BOUNDED_SEQUENCE: u8 = 96;
const UNBOUNDED_SEQUENCE: u8 = 144;

/// The id of a primitive `.msg` type (`char` is IDL's uint8 and `byte` an octet, as
/// rosidl_adapter maps them).
fn primitive_id(name: &str) -> Option<u8> {
    Some(match name {
        "int8" => 2,
        "uint8" | "char" => 3,
        "int16" => 4,
        "uint16" => 5,
        "int32" => 6,
        "uint32" => 7,
        "int64" => 8,
        "uint64" => 9,
        "float32" => 10,
        "float64" => 11,
        "bool" => 15,
        "byte" => 16,
        _ => return None,
    })
}

/// The fields of `type_name` (`pkg/msg/Name`) from its `.msg` text.
pub fn parse_fields(type_name: &str, text: &str) -> Result<Vec<Field>, MsgSyntaxError> {
    let package = type_name.split('/').next().unwrap_or_default();
    let mut fields = Vec::new();
    for (i, raw) in text.lines().enumerate() {
        let err = |reason: &str| MsgSyntaxError {
            type_name: type_name.to_owned(),
            line: i + 1,
            text: raw.to_owned(),
            reason: reason.to_owned(),
        };
        let line = raw.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let mut words = line.splitn(2, char::is_whitespace);
        let ty = words.next().unwrap_or_default();
        let rest = words.next().unwrap_or_default().trim_start();
        // A constant: `TYPE NAME=VALUE` (its value may hold a `#`); not part of the hash.
        if let Some((name, _)) = rest.split_once('=')
            && !name.trim().is_empty()
            && !name.trim().contains(char::is_whitespace)
        {
            continue;
        }
        let rest = rest.split('#').next().unwrap_or_default().trim();
        let name = rest.split_whitespace().next().ok_or_else(|| err("a type without a field name"))?;
        fields.push(Field { name: name.to_owned(), ty: parse_type(package, ty).map_err(|r| err(&r.to_string()))? });
    }
    Ok(fields)
}

/// Why a field's type does not parse.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
enum TypeSyntax {
    #[error("an array type without its closing `]`")]
    Unclosed,
    #[error("array bound `{0}` is not a number")]
    ArrayBound(String),
    #[error("string bound `{0}` is not a number")]
    StringBound(String),
    #[error("unknown type `{0}`")]
    Unknown(String),
}

/// `float64[7]`, `string<=16`, `labrig_msgs/RobotState[]`, `Header[<=3]`...
fn parse_type(package: &str, ty: &str) -> Result<FieldType, TypeSyntax> {
    let (element, offset, capacity) = match ty.split_once('[') {
        None => (ty, 0, 0),
        Some((element, bound)) => {
            let bound = bound.strip_suffix(']').ok_or(TypeSyntax::Unclosed)?;
            let number = |s: &str| s.parse::<u64>().map_err(|_| TypeSyntax::ArrayBound(s.to_owned()));
            match bound {
                "" => (element, UNBOUNDED_SEQUENCE, 0),
                b => match b.strip_prefix("<=") {
                    Some(max) => (element, BOUNDED_SEQUENCE, number(max)?),
                    None => (element, ARRAY, number(b)?),
                },
            }
        }
    };
    let (id, string_capacity, nested) = if let Some(id) = primitive_id(element) {
        (id, 0, String::new())
    } else if element == "string" {
        (STRING, 0, String::new())
    } else if element == "wstring" {
        (WSTRING, 0, String::new())
    } else if let Some(max) = element.strip_prefix("string<=") {
        (BOUNDED_STRING, max.parse().map_err(|_| TypeSyntax::StringBound(max.to_owned()))?, String::new())
    } else if let Some(max) = element.strip_prefix("wstring<=") {
        (BOUNDED_WSTRING, max.parse().map_err(|_| TypeSyntax::StringBound(max.to_owned()))?, String::new())
    } else {
        // Packages are snake_case, messages CamelCase (rosidl refuses others).
        let valid = |s: &str| !s.is_empty() && s.chars().all(|c| c.is_ascii_alphanumeric() || c == '_');
        let message = |s: &str| valid(s) && s.starts_with(|c: char| c.is_ascii_uppercase());
        let nested = match element.split('/').collect::<Vec<_>>()[..] {
            [name] if message(name) => format!("{package}/msg/{name}"),
            [pkg, name] if valid(pkg) && message(name) => format!("{pkg}/msg/{name}"),
            [pkg, "msg", name] if valid(pkg) && message(name) => format!("{pkg}/msg/{name}"),
            _ => return Err(TypeSyntax::Unknown(element.to_owned())),
        };
        (NESTED, 0, nested)
    };
    Ok(FieldType { type_id: id + offset, capacity, string_capacity, nested_type_name: nested })
}

/// A JSON string as Python's `json.dumps(ensure_ascii=True)` writes it.
fn json_string(s: &str, out: &mut String) {
    out.push('"');
    for c in s.chars() {
        match c {
            '"' => out.push_str("\\\""),
            '\\' => out.push_str("\\\\"),
            '\n' => out.push_str("\\n"),
            '\r' => out.push_str("\\r"),
            '\t' => out.push_str("\\t"),
            c if (c as u32) < 0x20 || (c as u32) > 0x7e => {
                let mut buf = [0u16; 2];
                for unit in c.encode_utf16(&mut buf) {
                    out.push_str(&format!("\\u{unit:04x}"));
                }
            }
            c => out.push(c),
        }
    }
    out.push('"');
}

/// One `IndividualTypeDescription` as the hash reads it.
fn describe(type_name: &str, fields: &[Field], out: &mut String) {
    out.push_str("{\"type_name\": ");
    json_string(type_name, out);
    out.push_str(", \"fields\": [");
    for (i, f) in fields.iter().enumerate() {
        if i > 0 {
            out.push_str(", ");
        }
        out.push_str("{\"name\": ");
        json_string(&f.name, out);
        out.push_str(&format!(
            ", \"type\": {{\"type_id\": {}, \"capacity\": {}, \"string_capacity\": {}, \"nested_type_name\": ",
            f.ty.type_id, f.ty.capacity, f.ty.string_capacity
        ));
        json_string(&f.ty.nested_type_name, out);
        out.push_str("}}");
    }
    out.push_str("]}");
}

/// A type whose `.msg` text refers to a type the definitions given lack.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum TypeHashError {
    #[error(transparent)]
    Syntax(#[from] MsgSyntaxError),
    #[error("{0} refers to {1}, whose definition is not given")]
    Missing(String, String),
}

/// The RIHS01 hash of `type_name` given its `.msg` text and every type it refers to, directly
/// or not, as `(pkg/msg/Name, .msg text)`.
pub fn type_hash_of(type_name: &str, text: &str, deps: &[(&str, &str)]) -> Result<String, TypeHashError> {
    let own = parse_fields(type_name, text)?;
    let mut referenced: std::collections::BTreeMap<String, Vec<Field>> = Default::default();
    let mut queue: Vec<(String, String)> = own
        .iter()
        .filter(|f| !f.ty.nested_type_name.is_empty())
        .map(|f| (type_name.to_owned(), f.ty.nested_type_name.clone()))
        .collect();
    while let Some((from, name)) = queue.pop() {
        if referenced.contains_key(&name) {
            continue;
        }
        let (_, text) =
            deps.iter().find(|(n, _)| *n == name).ok_or_else(|| TypeHashError::Missing(from.clone(), name.clone()))?;
        let fields = parse_fields(&name, text)?;
        queue.extend(
            fields
                .iter()
                .filter(|f| !f.ty.nested_type_name.is_empty())
                .map(|f| (name.clone(), f.ty.nested_type_name.clone())),
        );
        referenced.insert(name, fields);
    }
    let mut json = String::from("{\"type_description\": ");
    describe(type_name, &own, &mut json);
    json.push_str(", \"referenced_type_descriptions\": [");
    for (i, (name, fields)) in referenced.iter().enumerate() {
        if i > 0 {
            json.push_str(", ");
        }
        describe(name, fields, &mut json);
    }
    json.push_str("]}");
    let digest = Sha256::digest(json.as_bytes());
    Ok(format!("RIHS01_{}", digest.iter().map(|b| format!("{b:02x}")).collect::<String>()))
}

/// The RIHS01 hash of `T`.
pub fn type_hash<T: RosMessage>() -> String {
    let mut deps = Vec::new();
    T::dependencies(&mut deps);
    type_hash_of(T::TYPE_NAME, T::MSG_TEXT, &deps).expect("labrig's message definitions parse and are complete")
}

/// What rmw implementations put in an endpoint's USER_DATA QoS to announce its type's hash.
pub fn user_data(hash: &str) -> String {
    format!("typehash={hash};")
}

/// The type hash a peer announced in an endpoint's USER_DATA (`key=value;` pairs), if any:
/// the pairs as text, or the parameter's CDR value as discovery carries it (a little-endian
/// length, the bytes, padding).
pub fn from_user_data(user_data: &[u8]) -> Option<String> {
    let body = match user_data.get(..4).map(|n| u32::from_le_bytes([n[0], n[1], n[2], n[3]]) as usize) {
        Some(n) => user_data.get(4..4 + n).unwrap_or(user_data),
        None => user_data,
    };
    let text = std::str::from_utf8(body).ok()?;
    text.split(';')
        .find_map(|pair| pair.trim_matches('\0').strip_prefix("typehash="))
        .filter(|h| h.starts_with("RIHS"))
        .map(str::to_owned)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fields_parse_with_their_type_ids_bounds_and_nested_names() {
        let text = "# a comment\nuint8 K=3\nstring S=\"a#b\"\nfloat64[7] q  # trailing\nstring<=8 tag\n\
                    float32[] xs\nint16[<=4] ys\nHeader h\nsensor_msgs/Image[] images\nbyte b\nchar c\nbool ok true\n";
        let f = parse_fields("pkg/msg/T", text).unwrap();
        let got: Vec<(&str, u8, u64, u64, &str)> = f
            .iter()
            .map(|f| {
                (f.name.as_str(), f.ty.type_id, f.ty.capacity, f.ty.string_capacity, f.ty.nested_type_name.as_str())
            })
            .collect();
        assert_eq!(
            got,
            vec![
                ("q", 59, 7, 0, ""),
                ("tag", 21, 0, 8, ""),
                ("xs", 154, 0, 0, ""),
                ("ys", 100, 4, 0, ""),
                ("h", 1, 0, 0, "pkg/msg/Header"),
                ("images", 145, 0, 0, "sensor_msgs/msg/Image"),
                ("b", 16, 0, 0, ""),
                ("c", 3, 0, 0, ""),
                ("ok", 15, 0, 0, ""),
            ]
        );
        let e = parse_fields("pkg/msg/T", "flaot64 x\n").unwrap_err();
        assert_eq!((e.line, e.reason.as_str()), (1, "unknown type `flaot64`"));
        assert!(parse_fields("pkg/msg/T", "float64[3 x\n").unwrap_err().reason.contains("closing"));
        assert!(parse_fields("pkg/msg/T", "float64\n").unwrap_err().reason.contains("field name"));
    }

    #[test]
    fn comments_and_constants_leave_the_hash_alone_and_fields_change_it() {
        let h = |t: &str| type_hash_of("pkg/msg/T", t, &[]).unwrap();
        let base = h("int32 a\nstring b\n");
        assert_eq!(base, h("# doc\nuint8 K=1\nint32 a  # the a\n\nstring b\n"));
        assert_ne!(base, h("int32 a\nstring c\n"));
        assert_ne!(base, h("int64 a\nstring b\n"));
        assert_eq!(base.len(), "RIHS01_".len() + 64);
        assert!(matches!(type_hash_of("pkg/msg/T", "pkg2/U u\n", &[]), Err(TypeHashError::Missing(..))));
    }

    /// Hashes rosidl computed (its generator's `.json` files, Kilted wheels): a package's own
    /// type with a nested standard type, and std_msgs/Header.
    #[test]
    fn hashes_equal_the_ones_rosidl_computed() {
        let time = ("builtin_interfaces/msg/Time", "int32 sec\nuint32 nanosec\n");
        let step =
            "builtin_interfaces/Time stamp\nfloat64[7] joint_position\nfloat32[] action\nstring task\nuint8[] image\n";
        assert_eq!(
            type_hash_of("demo_msgs/msg/Step", step, &[time]).unwrap(),
            "RIHS01_1ebc8f71654f309f8f6c3a272bfde850307efd7fa4e89469b40b34b85c281acb"
        );
        assert_eq!(
            type_hash_of(time.0, time.1, &[]).unwrap(),
            "RIHS01_b106235e25a4c5ed35098aa0a61a3ee9c9b18d197f398b0e4206cea9acf9c197"
        );
        assert_eq!(
            type_hash::<crate::std_msgs::Header>(),
            "RIHS01_f49fb3ae2cf070f793645ff749683ac6b06203e41c891e17701b1cb597ce6a01"
        );
    }

    #[test]
    fn user_data_round_trips_and_reads_what_fast_dds_writes() {
        let h = format!("RIHS01_{}", "ab".repeat(32));
        assert_eq!(from_user_data(user_data(&h).as_bytes()), Some(h.clone()));
        assert_eq!(from_user_data(format!("enclave=/;typehash={h};").as_bytes()), Some(h.clone()));
        assert_eq!(from_user_data(b"enclave=/;\0"), None);
        // As RustDDS hands over Fast DDS's USER_DATA: the CDR length (81), the text, padding.
        let mut wire = 81u32.to_le_bytes().to_vec();
        wire.extend(user_data(&h).as_bytes());
        wire.extend([0, 0, 0]);
        assert_eq!(wire.len(), 88);
        assert_eq!(from_user_data(&wire), Some(h));
    }
}
