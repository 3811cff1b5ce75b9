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

/// Runs the rclpy peer's `cdr <direction>` over JSON lines; one answer per request. With
/// `fill`, glibc's malloc hands the peer every block filled with that byte (see
/// [`rclpy_serialize`]).
fn rclpy_cdr(direction: &str, requests: &[Value], fill: Option<u8>) -> Vec<Value> {
    let mut cmd = std::process::Command::new(labrig_tests::ros_python());
    cmd.arg(labrig_tests::repo_root().join("tests/peers/ros_peer.py")).args(["cdr", direction]);
    labrig_tests::ros_env(&mut cmd, labrig_tests::domain_for("cdr"));
    if let Some(fill) = fill {
        // glibc's perturb tunable fills each block malloc returns with the complement of its
        // value; tcache is off because blocks taken from it skip that fill.
        cmd.env("GLIBC_TUNABLES", format!("glibc.malloc.tcache_count=0:glibc.malloc.perturb={}", !fill));
    }
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

/// What `rclpy.serialization.serialize_message` returned for one message, and which of those
/// bytes it wrote.
struct RclpyBytes {
    /// serialize_message's bytes as returned (encapsulation header included), from the run
    /// where the bytes it does not write are 0x00.
    bytes: Vec<u8>,
    /// Per byte: serialize_message wrote it (the same in both runs).
    written: Vec<bool>,
}

impl RclpyBytes {
    /// One past the last byte serialize_message wrote: where its CDR data ends.
    fn end(&self) -> usize {
        self.written.iter().rposition(|&w| w).map_or(0, |i| i + 1)
    }

    /// The bytes labrig must send for this message: serialize_message's bytes up to the end
    /// of its data, the bytes it did not write (alignment padding) as zeros, and zero padding
    /// to a multiple of 4, which is the form Fast DDS puts on the wire.
    fn on_the_wire(&self) -> Vec<u8> {
        let mut out: Vec<u8> = self.bytes[..self.end()].to_vec();
        out.resize(self.end().next_multiple_of(4), 0);
        out
    }

    /// serialize_message's bytes in hex, `__` where it wrote nothing (for failure messages).
    fn annotated(&self) -> String {
        self.bytes.iter().zip(&self.written).map(|(b, &w)| if w { format!("{b:02x}") } else { "__".into() }).collect()
    }
}

/// rclpy's `serialize_message` of every request, run twice. rmw_serialize (what it calls) never
/// writes the CDR alignment padding, and sizes its freshly malloc'd buffer by an estimate that
/// can exceed the data, so those bytes hold whatever malloc left there (garbage that was
/// seen to differ from run to run). The peer runs once with malloc filling every block with 0x00 and
/// once with 0xAA: a byte equal in both runs is one serialize_message wrote, and every other
/// byte must be 0x00 in the first run and 0xAA in the second (else the fill did not reach it,
/// and nothing could tell it from data). No CDR layout knowledge goes into this split.
fn rclpy_serialize(types: &[String], samples: &BTreeMap<String, Value>) -> Vec<RclpyBytes> {
    let requests: Vec<Value> = types.iter().map(|t| json!({"type": t, "value": samples[t]})).collect();
    let zeros = rclpy_cdr("serialize", &requests, Some(0x00));
    let aas = rclpy_cdr("serialize", &requests, Some(0xAA));
    let mut out = Vec::new();
    for ((t, z), a) in types.iter().zip(&zeros).zip(&aas) {
        for answer in [z, a] {
            assert!(answer.get("error").is_none(), "rclpy could not serialize {t}: {answer}");
        }
        let (z, a) = (unhex(z["hex"].as_str().unwrap()), unhex(a["hex"].as_str().unwrap()));
        assert_eq!(z.len(), a.len(), "{t}: serialize_message returned different lengths for the same message");
        let written: Vec<bool> = z.iter().zip(&a).map(|(x, y)| x == y).collect();
        for (i, (&x, &y)) in z.iter().zip(&a).enumerate() {
            assert!(
                x == y || (x, y) == (0x00, 0xAA),
                "{t}: byte {i} is neither written nor malloc's fill: {x:02x} / {y:02x}"
            );
        }
        out.push(RclpyBytes { bytes: z, written });
    }
    out
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
    let rclpy = rclpy_serialize(&types, &samples);
    for (t, r) in types.iter().zip(&rclpy) {
        // Compared exactly, over labrig's whole buffer: the 4-byte encapsulation header
        // (00 01 00 00: plain CDR little endian, no options) and every byte serialize_message
        // wrote are rclpy's own bytes; where serialize_message wrote nothing (alignment
        // padding) labrig has zeros; labrig's buffer ends at serialize_message's last written
        // byte, zero padded to a multiple of 4. serialize_message's own length is not
        // compared: it is rmw's size estimate (4 bytes past the data for the sample
        // JointState), and it leaves out that final padding (26 bytes for the sample Header).
        let ours = visit_type(t, Encode(samples[t].clone())).unwrap();
        assert_eq!(
            hex(&ours),
            hex(&r.on_the_wire()),
            "{t}: labrig's CDR differs from rclpy's serialize_message {} (__: not written by rclpy)",
            r.annotated()
        );
        // And labrig reads rclpy's bytes back to the sample, padded as on the wire and
        // as serialize_message leaves them (cut after its last written byte).
        visit_type(t, DecodeEquals(r.on_the_wire(), samples[t].clone())).unwrap();
        visit_type(t, DecodeEquals(r.bytes[..r.end()].to_vec(), samples[t].clone())).unwrap();
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
    let answers = rclpy_cdr("deserialize", &requests, None);
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
    let wire = rclpy_serialize(&[t.to_owned()], &samples)[0].on_the_wire();
    let err = decode::<labrig_msgs::sensor_msgs::CameraInfo>(&wire[..wire.len() / 2]).unwrap_err();
    assert!(err.to_string().starts_with("sensor_msgs/msg/CameraInfo: malformed or truncated"), "{err}");
}
