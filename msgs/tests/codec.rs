//! Codec properties for every message type: round trip, truncation, trailing garbage, random
//! bytes. Sample values come from `fixtures/samples.json` (the same file the rclpy byte-for-byte
//! test in `tests/` feeds to ROS 2).

use labrig_msgs::{CodecError, RosMessage, TypeVisitor, decode, encode, known_types, visit_type};
use proptest::prelude::*;
use serde_json::Value;
use std::collections::BTreeMap;

fn samples() -> BTreeMap<String, Value> {
    serde_json::from_str(include_str!("fixtures/samples.json")).expect("samples.json parses")
}

/// Encodes the JSON sample of a type through its Rust type.
struct EncodeSample(Value);
impl TypeVisitor for EncodeSample {
    type Output = Vec<u8>;
    fn visit<T: RosMessage>(self) -> Vec<u8> {
        let msg: T = serde_json::from_value(self.0).unwrap_or_else(|e| panic!("{}: sample: {e}", T::TYPE_NAME));
        let bytes = encode(&msg).unwrap();
        let back: T = decode(&bytes).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(back, msg, "{} round trip", T::TYPE_NAME);
        bytes
    }
}

/// Decodes and reports whether it worked (the error must name the type) and, if so, whether
/// the type has an earlier layout (a body in it decodes too) and the value as JSON.
struct TryDecode<'a>(&'a [u8]);
impl TypeVisitor for TryDecode<'_> {
    type Output = Result<(bool, Value), String>;
    fn visit<T: RosMessage>(self) -> Result<(bool, Value), String> {
        match decode::<T>(self.0) {
            Ok(m) => Ok((T::decode_legacy([0, 1], &[]).is_some(), serde_json::to_value(m).unwrap())),
            Err(e) => {
                let text = e.to_string();
                assert!(text.starts_with(T::TYPE_NAME), "error does not name the type: {text}");
                Err(text)
            }
        }
    }
}

#[test]
fn every_known_type_has_a_sample_and_round_trips() {
    let samples = samples();
    for &name in known_types() {
        let sample = samples.get(name).unwrap_or_else(|| panic!("no sample for {name}"));
        let bytes = visit_type(name, EncodeSample(sample.clone())).unwrap();
        assert_eq!(&bytes[..2], &[0x00, 0x01], "{name}: CDR little-endian header");
        assert_eq!(bytes.len() % 4, 0, "{name}: padded to 4 bytes");
    }
}

#[test]
fn every_truncation_of_every_sample_is_an_error_naming_the_type() {
    for (name, sample) in samples() {
        let bytes = visit_type(&name, EncodeSample(sample.clone())).unwrap();
        for cut in 0..bytes.len() {
            let r = visit_type(&name, TryDecode(&bytes[..cut])).unwrap();
            // Cutting only final alignment padding leaves a valid (unpadded) encoding, which is
            // what rclpy's serialize_message returns; cutting into the body must fail.
            let only_padding_cut = bytes.len() - cut <= 3 && bytes[cut..].iter().all(|&b| b == 0);
            if only_padding_cut {
                continue;
            }
            // A type that grew fields decodes a body cut where its earlier layout ended: the
            // sample's values with the new fields empty; any other cut fails.
            if let Ok((true, Value::Object(got))) = &r {
                let Value::Object(want) = &sample else { panic!("{name}: sample is not an object") };
                let grown: Vec<&String> = want.keys().filter(|k| got[*k] != want[*k]).collect();
                let empty = |v: &Value| matches!(v, Value::String(s) if s.is_empty()) || v == &Value::from(0);
                assert!(
                    !grown.is_empty() && grown.iter().all(|k| empty(&got[*k])),
                    "{name}: the first {cut} of {} bytes decoded to another value ({grown:?} differ)",
                    bytes.len()
                );
                continue;
            }
            assert!(r.is_err(), "{name}: decoding the first {cut} of {} bytes succeeded", bytes.len());
        }
    }
}

#[test]
fn trailing_garbage_is_an_error_naming_the_type() {
    for (name, sample) in samples() {
        let bytes = visit_type(&name, EncodeSample(sample)).unwrap();
        for garbage in [&[0xABu8][..], &[0, 0, 0, 0], &[1, 2, 3, 4, 5, 6, 7, 8]] {
            let mut b = bytes.clone();
            b.extend_from_slice(garbage);
            let err = visit_type(&name, TryDecode(&b)).unwrap().unwrap_err();
            assert!(err.contains("unexpected bytes"), "{name}: {err}");
        }
    }
}

#[test]
fn wrong_schema_version_is_refused_with_both_versions_named() {
    let mut step = labrig_msgs::rig::Step::default();
    step.version.0 = 2;
    let bytes = encode(&step).unwrap();
    let err = decode::<labrig_msgs::rig::Step>(&bytes).unwrap_err();
    assert!(matches!(err, CodecError::Invalid { .. }));
    assert_eq!(
        err.to_string(),
        "labrig_msgs/msg/Step: invalid value: schema version 2 is not supported (this build reads version 1)"
    );
}

#[test]
fn unknown_encapsulation_is_refused() {
    let err = decode::<labrig_msgs::std_msgs::Header>(&[0x00, 0x07, 0, 0, 0, 0, 0, 0]).unwrap_err();
    assert!(err.to_string().contains("unsupported encapsulation [00, 07]"), "{err}");
}

#[test]
fn big_endian_cdr_decodes_too() {
    // builtin_interfaces/Time {sec: 1, nanosec: 2} in CDR big endian.
    let t: labrig_msgs::builtin_interfaces::Time = decode(&[0, 0, 0, 0, 0, 0, 0, 1, 0, 0, 0, 2]).unwrap();
    assert_eq!((t.sec, t.nanosec), (1, 2));
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 512, .. ProptestConfig::default() })]

    /// No byte string makes any decoder panic; failures name the type.
    #[test]
    fn random_bytes_never_panic_any_decoder(bytes in proptest::collection::vec(any::<u8>(), 0..256), le in any::<bool>()) {
        let mut b = bytes;
        if b.len() >= 2 && le { b[0] = 0; b[1] = 1; }
        for &name in known_types() {
            let _ = visit_type(name, TryDecode(&b)).unwrap();
        }
    }

    /// Single-byte corruptions of valid encodings never panic a decoder.
    #[test]
    fn corrupted_samples_never_panic(index in any::<prop::sample::Index>(), byte in any::<u8>(), which in any::<prop::sample::Index>()) {
        let samples = samples();
        let (name, sample) = samples.iter().nth(which.index(samples.len())).unwrap();
        let mut bytes = visit_type(name, EncodeSample(sample.clone())).unwrap();
        let i = index.index(bytes.len());
        bytes[i] = byte;
        let _ = visit_type(name, TryDecode(&bytes)).unwrap();
    }
}
