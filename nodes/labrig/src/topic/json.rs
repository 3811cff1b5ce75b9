//! Decoding any known message type to JSON by its ROS type name.

use labrig_msgs::{CodecError, RosMessage, TypeVisitor, decode_payload, visit_type};
use serde_json::Value;

struct ToJson<'a> {
    encoding: [u8; 2],
    payload: &'a [u8],
}

impl TypeVisitor for ToJson<'_> {
    type Output = Result<Value, CodecError>;
    fn visit<T: RosMessage>(self) -> Self::Output {
        let msg = decode_payload::<T>(self.encoding, self.payload)?;
        Ok(serde_json::to_value(&msg).expect("message types serialise to JSON"))
    }
}

/// Decodes a CDR body of the named type to JSON; `None` if labrig does not know the type.
pub fn decode_to_json(type_name: &str, encoding: [u8; 2], payload: &[u8]) -> Option<Result<Value, CodecError>> {
    visit_type(type_name, ToJson { encoding, payload })
}

/// Replaces arrays longer than `max` (image data, long sequences) by a short summary string,
/// for human-readable output.
pub fn abbreviate(value: &mut Value, max: usize) {
    match value {
        Value::Array(items) if items.len() > max => {
            *value = Value::String(format!("<array of {} elements>", items.len()));
        }
        Value::Array(items) => items.iter_mut().for_each(|v| abbreviate(v, max)),
        Value::Object(map) => map.values_mut().for_each(|v| abbreviate(v, max)),
        _ => {}
    }
}

/// Renders JSON as indented `key: value` lines, like `ros2 topic echo`.
pub fn to_yamlish(value: &Value, indent: usize, out: &mut String) {
    let pad = "  ".repeat(indent);
    match value {
        Value::Object(map) => {
            for (k, v) in map {
                match v {
                    Value::Object(_) => {
                        out.push_str(&format!("{pad}{k}:\n"));
                        to_yamlish(v, indent + 1, out);
                    }
                    Value::Array(items) if items.iter().any(|i| i.is_object()) => {
                        out.push_str(&format!("{pad}{k}:\n"));
                        for item in items {
                            out.push_str(&format!("{pad}- \n"));
                            to_yamlish(item, indent + 1, out);
                        }
                    }
                    _ => out.push_str(&format!("{pad}{k}: {v}\n")),
                }
            }
        }
        other => out.push_str(&format!("{pad}{other}\n")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use labrig_msgs::geometry_msgs::Twist;

    #[test]
    fn known_types_decode_to_json_unknown_ones_are_none() {
        let mut t = Twist::default();
        t.linear.x = 1.5;
        let bytes = labrig_msgs::encode(&t).unwrap();
        let v = decode_to_json("geometry_msgs::msg::dds_::Twist_", [0, 1], &bytes[4..]).unwrap().unwrap();
        assert_eq!(v["linear"]["x"], 1.5);
        assert!(decode_to_json("foo_msgs/msg/Bar", [0, 1], &bytes[4..]).is_none());
        let err = decode_to_json("geometry_msgs/msg/Twist", [0, 1], &bytes[4..10]).unwrap().unwrap_err();
        assert!(err.to_string().starts_with("geometry_msgs/msg/Twist"));
    }

    #[test]
    fn long_arrays_are_abbreviated() {
        let mut v = serde_json::json!({"data": vec![0u8; 100], "name": ["a", "b"]});
        abbreviate(&mut v, 32);
        assert_eq!(v["data"], "<array of 100 elements>");
        assert_eq!(v["name"][1], "b");
    }
}
