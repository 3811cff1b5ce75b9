//! Byte-for-byte CDR agreement with ROS 2 itself (rclpy's serialize_message/deserialize_message
//! from the PyPI ros-* wheels), for every standard type those wheels carry, on the sample
//! values of `msgs/tests/fixtures/samples.json`.

use labrig_msgs::{RosMessage, TypeVisitor, decode, encode, visit_type};
use serde_json::{Value, json};
use std::collections::BTreeMap;
use std::io::Write;

/// Types labrig shares with ROS 2 and the PyPI wheels carry (tf2_msgs is not among them;
/// labrig_msgs is labrig's own).
fn ros_types(samples: &BTreeMap<String, Value>) -> Vec<String> {
    samples.keys().filter(|t| !t.starts_with("labrig_msgs/") && !t.starts_with("tf2_msgs/")).cloned().collect()
}

fn samples() -> BTreeMap<String, Value> {
    let text = std::fs::read_to_string(labrig_tests::repo_root().join("msgs/tests/fixtures/samples.json")).unwrap();
    serde_json::from_str(&text).unwrap()
}

/// Runs the rclpy peer's `cdr <direction>` over JSON lines; one answer per request.
fn rclpy_cdr(direction: &str, requests: &[Value]) -> Vec<Value> {
    let mut cmd = std::process::Command::new(labrig_tests::ros_python());
    cmd.arg(labrig_tests::repo_root().join("tests/peers/ros_peer.py")).args(["cdr", direction]);
    labrig_tests::ros_env(&mut cmd, labrig_tests::domain_for("cdr"));
    cmd.stdin(std::process::Stdio::piped()).stdout(std::process::Stdio::piped());
    let mut proc = cmd.spawn().expect("rclpy peer");
    let mut stdin = proc.stdin.take().unwrap();
    for r in requests {
        writeln!(stdin, "{r}").unwrap();
    }
    drop(stdin);
    let out = proc.wait_with_output().unwrap();
    assert!(out.status.success(), "rclpy cdr {direction} failed: {:?}", out.status);
    let answers: Vec<Value> =
        String::from_utf8(out.stdout).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert_eq!(answers.len(), requests.len(), "one answer per request");
    answers
}

struct Encode(Value);
impl TypeVisitor for Encode {
    type Output = Vec<u8>;
    fn visit<T: RosMessage>(self) -> Vec<u8> {
        encode(&serde_json::from_value::<T>(self.0).unwrap()).unwrap()
    }
}

/// Decodes rclpy's bytes with labrig and checks the value equals the sample.
struct DecodeEquals(Vec<u8>, Value);
impl TypeVisitor for DecodeEquals {
    type Output = ();
    fn visit<T: RosMessage>(self) {
        let expected: T = serde_json::from_value(self.1).unwrap();
        let got: T = decode(&self.0).unwrap_or_else(|e| panic!("labrig cannot decode rclpy's bytes: {e}"));
        assert_eq!(got, expected, "{}", T::TYPE_NAME);
    }
}

fn hex(b: &[u8]) -> String {
    b.iter().map(|x| format!("{x:02x}")).collect()
}

fn unhex(s: &str) -> Vec<u8> {
    (0..s.len()).step_by(2).map(|i| u8::from_str_radix(&s[i..i + 2], 16).unwrap()).collect()
}

#[test]
fn labrig_bytes_equal_ros2_bytes_for_every_standard_type() {
    let samples = samples();
    let types = ros_types(&samples);
    assert!(types.len() >= 20, "expected every standard type, got {types:?}");
    let requests: Vec<Value> = types.iter().map(|t| json!({"type": t, "value": samples[t]})).collect();
    let answers = rclpy_cdr("serialize", &requests);
    for (t, a) in types.iter().zip(&answers) {
        assert!(a.get("error").is_none(), "rclpy could not serialize {t}: {a}");
        // rclpy's serialize_message leaves alignment padding uninitialised and may report a
        // few bytes too many; `wire_hex` is the same serialization with padding zeroed and
        // cut to what Fast DDS sends (checked against captured packets when the peer was
        // written). The raw `hex` must agree with it on every data byte.
        let wire = a["wire_hex"].as_str().unwrap();
        let ours = visit_type(t, Encode(samples[t].clone())).unwrap();
        assert_eq!(hex(&ours), wire, "{t}: labrig's CDR differs from ROS 2's");
        let raw = unhex(a["hex"].as_str().unwrap());
        assert!(raw.len() + 3 >= ours.len(), "{t}: rclpy produced fewer bytes than labrig");
        visit_type(t, DecodeEquals(unhex(wire), samples[t].clone())).unwrap();
    }
}

/// Floats from rclpy come back as JSON numbers; compare numerically, everything else exactly.
fn same(a: &Value, b: &Value) -> bool {
    match (a, b) {
        (Value::Number(x), Value::Number(y)) => x.as_f64() == y.as_f64(),
        (Value::Array(x), Value::Array(y)) => x.len() == y.len() && x.iter().zip(y).all(|(p, q)| same(p, q)),
        (Value::Object(x), Value::Object(y)) => {
            x.len() == y.len() && x.iter().all(|(k, v)| y.get(k).is_some_and(|w| same(v, w)))
        }
        _ => a == b,
    }
}

#[test]
fn ros2_decodes_labrig_bytes_to_the_same_values() {
    let samples = samples();
    let types = ros_types(&samples);
    let requests: Vec<Value> = types
        .iter()
        .map(|t| json!({"type": t, "hex": hex(&visit_type(t, Encode(samples[t].clone())).unwrap())}))
        .collect();
    let answers = rclpy_cdr("deserialize", &requests);
    for (t, a) in types.iter().zip(&answers) {
        assert!(a.get("error").is_none(), "rclpy could not deserialize labrig's {t}: {a}");
        assert!(same(&a["value"], &samples[t]), "{t}: rclpy read {} but labrig wrote {}", a["value"], samples[t]);
    }
}

#[test]
fn a_corrupted_rclpy_buffer_is_an_error_naming_the_type() {
    // A real ROS 2 buffer, cut short: the error names the type, and nothing panics.
    let samples = samples();
    let t = "sensor_msgs/msg/CameraInfo";
    let a = &rclpy_cdr("serialize", &[json!({"type": t, "value": samples[t]})])[0];
    let wire = unhex(a["wire_hex"].as_str().unwrap());
    let err = decode::<labrig_msgs::sensor_msgs::CameraInfo>(&wire[..wire.len() / 2]).unwrap_err();
    assert!(err.to_string().starts_with("sensor_msgs/msg/CameraInfo: malformed or truncated"), "{err}");
}
