//! Bad input never panics: the episode reader (`inspect`, `read_episode`) and `recover` on
//! truncated, bit-flipped and overwritten episode files, on arbitrary bytes (with and without
//! MCAP's magic), on well-framed records of arbitrary content, and on well-formed files whose
//! values are arbitrary (log times, step timings, garbage payloads of known types).
//!
//! Each property: no panic; a file is either read (damage reported in the inspection) or a
//! typed error naming the file. A truncated file recovers into one that `inspect` reads as
//! complete, holding no more messages than the original.

use labrig_episode::bag::Reliability;
use labrig_episode::recover::recover;
use labrig_episode::{EpisodeMetadata, EpisodeWriter, ReadError, RigIdentity, inspect, read_episode};
use labrig_msgs::Nanos;
use labrig_msgs::labrig_msgs::{CameraFrameRef, ControlTiming, RobotState, Step};
use labrig_msgs::sensor_msgs::CompressedImage;
use labrig_msgs::std_msgs::Header;
use proptest::prelude::*;
use std::collections::BTreeMap;
use std::path::Path;
use std::sync::OnceLock;

const T0: i64 = 1_795_000_000_000_000_000;
const TICK: i64 = 50_000_000;

fn header(t: i64, frame: &str) -> Header {
    Header { stamp: Nanos(t).into(), frame_id: frame.into() }
}

/// A small finished episode: 3.5 s of steps at 20 Hz, one camera, /arm/state at 50 Hz, an
/// attachment; four closed chunks, the DROID record first and last. Its bytes and messages.
fn episode() -> &'static (Vec<u8>, u64) {
    static EPISODE: OnceLock<(Vec<u8>, u64)> = OnceLock::new();
    EPISODE.get_or_init(|| {
        let tmp = tempfile::tempdir().unwrap();
        let mut meta =
            EpisodeMetadata::new(&RigIdentity::default(), "pick_place_cube", "put the cube in the bin", Nanos(T0));
        meta.extrinsics.insert("ext1".into(), [0.5, -0.4, 0.6, 0.1, 0.2, 0.3]);
        meta.sim_scene = Some(r#"{"seed": 3}"#.into());
        let mut w = EpisodeWriter::create(tmp.path(), meta).unwrap();
        w.attach("scene.json", "application/json", br#"{"seed": 3}"#, Nanos(T0)).unwrap();
        for k in 0..175i64 {
            let t = T0 + k * 20_000_000;
            let state =
                RobotState { header: header(t, "base"), joint_positions: [k as f64 * 0.01; 7], ..Default::default() };
            w.write("/arm/state", &state, Nanos(t), Nanos(t), Reliability::Reliable).unwrap();
        }
        for k in 0..70i64 {
            let t = T0 + k * TICK;
            let img = CompressedImage {
                header: header(t, "ext1_optical"),
                format: "jpeg".into(),
                data: (0..64).map(|i| (i + k) as u8).collect(),
            };
            w.write("/cameras/ext1/image/compressed", &img, Nanos(t + 1_000), Nanos(t), Reliability::BestEffort)
                .unwrap();
            let step = Step {
                header: header(t, "base"),
                episode_id: "e".into(),
                step_index: k as u64,
                cameras: vec![CameraFrameRef {
                    camera_id: "ext1".into(),
                    capture_ns: t,
                    arrival_ns: t,
                    ..Default::default()
                }],
                timing: ControlTiming { step_start: t, ..Default::default() },
                action_source: Step::SOURCE_SCRIPTED,
                ..Default::default()
            };
            w.write("/rig/step", &step, Nanos(t + 2_000), Nanos(t), Reliability::Reliable).unwrap();
        }
        w.metadata_mut().success = Some(true);
        w.metadata_mut().trajectory_length = 70;
        let summary = w.finish().unwrap();
        assert!(summary.messages == 175 + 2 * 70);
        let bytes = std::fs::read(tmp.path().join("episode_0.mcap")).unwrap();
        (bytes, summary.messages)
    })
}

/// Where the MCAP header record ends (magic, opcode, length, content): a file cut before it
/// has nothing to recover.
fn header_end(bytes: &[u8]) -> usize {
    let len = u64::from_le_bytes(bytes[9..17].try_into().unwrap());
    17 + len as usize
}

/// What the readers make of `bytes`, written as an episode file.
struct Outcome {
    inspected: Result<labrig_episode::Inspection, ReadError>,
    recovered: Result<(labrig_episode::recover::RecoverReport, labrig_episode::Inspection), String>,
}

/// Runs every reader on `bytes` (as a file, as the one part of a directory) and checks what
/// holds for any input: no panic; errors name the file; a recovered file reads back complete
/// with the messages recover reported.
fn read_all(bytes: &[u8]) -> Outcome {
    let tmp = tempfile::tempdir().unwrap();
    let file = tmp.path().join("episode_0.mcap");
    std::fs::write(&file, bytes).unwrap();
    let inspected = inspect(&file);
    match &inspected {
        Ok(i) => {
            let _ = i.text();
            assert_eq!(i.messages, i.topics.iter().map(|t| t.count).sum::<u64>());
        }
        Err(e) => assert_names(&e.to_string(), &file),
    }
    match read_episode(&file) {
        Ok(d) => assert!(d.steps.windows(2).all(|w| w[0].step_index < w[1].step_index)),
        Err(e) => assert_names(&e.to_string(), &file),
    }
    // The directory holding it: the same reading.
    assert_eq!(inspect(tmp.path()).is_ok(), inspected.is_ok());
    let out_dir = tmp.path().join("recovered");
    std::fs::create_dir(&out_dir).unwrap();
    let out = out_dir.join("episode_0.mcap");
    let recovered = match recover(&file, &out) {
        Ok(report) => {
            let back = inspect(&out).unwrap_or_else(|e| panic!("the recovered file does not read: {e}"));
            assert!(back.complete, "a recovered file is finished: {:?}", back.damage);
            assert_eq!(back.damage, None);
            assert_eq!(back.messages, report.messages, "{report:?}");
            Ok((report, back))
        }
        Err(e) => {
            let text = e.to_string();
            assert!(
                text.contains(&file.display().to_string()) || text.contains(&out.display().to_string()),
                "recover's error names neither file: {text}"
            );
            Err(text)
        }
    };
    recover_dir(tmp.path(), &[bytes]);
    Outcome { inspected, recovered }
}

/// `labrig recover <dir>` on a directory of these parts (a copy under `tmp`): it recovers
/// what it can or names what it cannot; after it, the directory reads as finished.
fn recover_dir(tmp: &Path, parts: &[&[u8]]) {
    let dir = tmp.join("in_place");
    std::fs::create_dir(&dir).unwrap();
    for (k, b) in parts.iter().enumerate() {
        std::fs::write(dir.join(format!("episode_{k}.mcap")), b).unwrap();
    }
    let before = inspect(&dir);
    let _ = read_episode(&dir);
    match labrig_episode::recover::recover_in_place(&dir) {
        Ok(_) => {
            let after = inspect(&dir).unwrap_or_else(|e| panic!("a recovered directory does not read: {e}"));
            assert!(after.complete, "{:?}", after.flags);
            assert!(dir.join("metadata.yaml").is_file());
            if let Ok(before) = before {
                assert!(after.messages <= before.messages, "recovery invented messages");
            }
            let _ = read_episode(&dir);
        }
        Err(e) => assert_names(&e.to_string(), &dir),
    }
}

/// The error names `path` (or, for a directory, a file in it).
fn assert_names(text: &str, path: &Path) {
    assert!(text.contains(&path.display().to_string()), "the error does not name {}: {text}", path.display());
}

/// MCAP's record opcodes (header .. data end) and a few unknown ones.
fn opcode() -> impl Strategy<Value = u8> {
    prop_oneof![8 => 0x01u8..=0x0F, 1 => any::<u8>()]
}

/// Type names the reader decodes specially or through the registry, and unknown ones.
fn type_name() -> impl Strategy<Value = String> {
    prop_oneof![
        Just("labrig_msgs/msg/Step".to_owned()),
        Just("sensor_msgs/msg/CompressedImage".to_owned()),
        Just("labrig_msgs/msg/RobotState".to_owned()),
        Just("sensor_msgs/msg/CameraInfo".to_owned()),
        Just("tf2_msgs/msg/TFMessage".to_owned()),
        Just("sensor_msgs::msg::dds_::JointState_".to_owned()),
        ".{0,24}",
    ]
}

/// Log times the recorder writes (i64 nanoseconds, never negative); see
/// `a_log_time_past_i64_does_not_overflow_the_duration` for the rest of u64's range.
fn log_time() -> impl Strategy<Value = u64> {
    prop_oneof![Just(0u64), Just(i64::MAX as u64), 0u64..=i64::MAX as u64, (T0 as u64)..(T0 as u64 + 10 * TICK as u64)]
}

/// Step times: ordinary ones near T0 and extremes whose differences overflow in the spans the
/// inspection computes are left to the `#[ignore]`d findings below.
fn step_time() -> impl Strategy<Value = i64> {
    prop_oneof![Just(0i64), T0..T0 + 100 * TICK, -(1i64 << 61)..(1i64 << 61)]
}

fn step() -> impl Strategy<Value = Step> {
    (
        any::<u64>(),
        step_time(),
        step_time(),
        prop::collection::vec((".{0,6}", step_time()), 0..4),
        any::<i32>(),
        any::<u32>(),
    )
        .prop_map(|(index, start, end, cams, sec, nanosec)| Step {
            header: Header { stamp: labrig_msgs::builtin_interfaces::Time { sec, nanosec }, frame_id: "base".into() },
            step_index: index,
            cameras: cams
                .into_iter()
                .map(|(id, t)| CameraFrameRef { camera_id: id, capture_ns: t, arrival_ns: t, ..Default::default() })
                .collect(),
            timing: ControlTiming { step_start: start, step_end: end, ..Default::default() },
            ..Default::default()
        })
}

/// One message of an adversarial file: its channel's type and topic, log time, payload.
#[derive(Debug, Clone)]
enum Payload {
    Bytes(Vec<u8>),
    Step(Step),
    Image(i32, Vec<u8>),
}

fn message() -> impl Strategy<Value = (String, String, u64, Payload)> {
    let payload = prop_oneof![
        prop::collection::vec(any::<u8>(), 0..64).prop_map(Payload::Bytes),
        // A valid encapsulation header and a body of any bytes.
        prop::collection::vec(any::<u8>(), 0..64).prop_map(|b| Payload::Bytes([vec![0, 1, 0, 0], b].concat())),
        step().prop_map(Payload::Step),
        (any::<i32>(), prop::collection::vec(any::<u8>(), 0..8)).prop_map(|(s, d)| Payload::Image(s, d)),
    ];
    (
        type_name(),
        prop_oneof![Just("/rig/step".to_owned()), "/cameras/[a-z0-9]{0,4}/image/compressed", ".{0,12}"],
        log_time(),
        payload,
    )
}

/// A file written by the MCAP library itself, with adversarial content: channels of any type
/// carrying any payload at any log time, and a DROID record of any keys and values.
fn adversarial_file(
    messages: &[(String, String, u64, Payload)],
    droid: &BTreeMap<String, String>,
    finish: bool,
) -> Vec<u8> {
    let mut w = mcap::Writer::new(std::io::Cursor::new(Vec::new())).unwrap();
    w.write_metadata(&mcap::records::Metadata { name: "droid_episode".into(), metadata: droid.clone() }).unwrap();
    let mut channels: BTreeMap<(String, String), u16> = BTreeMap::new();
    for (seq, (ty, topic, log, payload)) in messages.iter().enumerate() {
        let id = match channels.get(&(ty.clone(), topic.clone())) {
            Some(&id) => id,
            None => {
                let schema = w.add_schema(ty, "ros2msg", b"").unwrap();
                let id = w.add_channel(schema, topic, "cdr", &BTreeMap::new()).unwrap();
                channels.insert((ty.clone(), topic.clone()), id);
                id
            }
        };
        let data = match payload {
            Payload::Bytes(b) => b.clone(),
            Payload::Step(s) => labrig_msgs::encode(s).unwrap_or_default(),
            Payload::Image(sec, d) => labrig_msgs::encode(&CompressedImage {
                header: Header {
                    stamp: labrig_msgs::builtin_interfaces::Time { sec: *sec, nanosec: 0 },
                    frame_id: String::new(),
                },
                format: "jpeg".into(),
                data: d.clone(),
            })
            .unwrap_or_default(),
        };
        let h =
            mcap::records::MessageHeader { channel_id: id, sequence: seq as u32, log_time: *log, publish_time: *log };
        w.write_to_known_channel(&h, &data).unwrap();
    }
    if finish {
        w.finish().unwrap();
    } else {
        w.flush().unwrap();
    }
    w.into_inner().into_inner()
}

fn droid_record() -> impl Strategy<Value = BTreeMap<String, String>> {
    let good = EpisodeMetadata::new(&RigIdentity::default(), "s", "t", Nanos(T0)).to_record();
    let keys: Vec<String> = good.keys().cloned().collect();
    (Just(good), prop::collection::vec((prop::sample::select(keys), ".{0,12}"), 0..4), any::<bool>()).prop_map(
        |(mut m, edits, drop_one)| {
            for (k, v) in edits {
                if drop_one {
                    m.remove(&k);
                } else {
                    m.insert(k, v);
                }
            }
            m
        },
    )
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(192))]

    /// Cut anywhere: the readers read up to the cut; recover gives a complete file with at
    /// most the original's messages, whenever the header survived.
    #[test]
    fn a_truncated_episode_reads_up_to_the_cut_and_recovers(at in any::<prop::sample::Index>()) {
        let (bytes, total) = episode();
        let cut = at.index(bytes.len() + 1);
        let o = read_all(&bytes[..cut]);
        if cut >= 8 {
            let i = o.inspected.as_ref().expect("a cut file with its magic is read up to the cut");
            prop_assert!(i.messages <= *total);
            prop_assert_eq!(i.complete, cut == bytes.len());
        }
        if cut >= header_end(bytes) {
            let (report, back) = o.recovered.as_ref().expect("a file with its header recovers");
            prop_assert!(report.messages <= *total && back.messages <= *total, "{:?}", report);
        }
    }

    /// Bits flipped anywhere: read or refused, never a panic.
    #[test]
    fn a_bit_flipped_episode_never_panics(flips in prop::collection::vec((any::<prop::sample::Index>(), 0u8..8), 1..8)) {
        let (bytes, _) = episode();
        let mut b = bytes.clone();
        for (at, bit) in flips {
            let i = at.index(b.len());
            b[i] ^= 1 << bit;
        }
        read_all(&b);
    }

    /// An episode recorded in two parts (a recorder restart), the second one cut and damaged:
    /// the directory reads and recovers, or the error names it.
    #[test]
    fn a_damaged_second_part_never_panics(
        at in any::<prop::sample::Index>(),
        flips in prop::collection::vec((any::<prop::sample::Index>(), 0u8..8), 0..4),
    ) {
        let (bytes, _) = episode();
        let mut b = bytes[..at.index(bytes.len() + 1)].to_vec();
        for (at, bit) in flips {
            if !b.is_empty() {
                let i = at.index(b.len());
                b[i] ^= 1 << bit;
            }
        }
        let tmp = tempfile::tempdir().unwrap();
        recover_dir(tmp.path(), &[bytes, &b]);
    }

    /// A byte range overwritten with anything (a torn write, another file's blocks).
    #[test]
    fn an_overwritten_range_never_panics(at in any::<prop::sample::Index>(), junk in prop::collection::vec(any::<u8>(), 1..256), cut in any::<bool>()) {
        let (bytes, _) = episode();
        let mut b = bytes.clone();
        let start = at.index(b.len());
        let end = (start + junk.len()).min(b.len());
        b[start..end].copy_from_slice(&junk[..end - start]);
        if cut {
            b.truncate(end);
        }
        read_all(&b);
    }

    /// Any bytes at all, with or without the magic in front.
    #[test]
    fn arbitrary_bytes_never_panic(magic in any::<bool>(), body in prop::collection::vec(any::<u8>(), 0..2048)) {
        let b = if magic { [mcap::MAGIC, &body].concat() } else { body };
        let o = read_all(&b);
        if !b.starts_with(mcap::MAGIC) {
            prop_assert!(matches!(o.inspected, Err(ReadError::NotMcap { .. })), "{:?}", o.inspected.err());
        }
    }

    /// Well-framed records (known opcodes, right lengths) of arbitrary content: every record
    /// parser sees garbage.
    #[test]
    fn framed_records_of_arbitrary_content_never_panic(
        keep_header in any::<bool>(),
        records in prop::collection::vec((opcode(), prop::collection::vec(any::<u8>(), 0..96)), 0..12),
        end_magic in any::<bool>(),
    ) {
        let (bytes, _) = episode();
        let mut b = if keep_header { bytes[..header_end(bytes)].to_vec() } else { mcap::MAGIC.to_vec() };
        for (op, content) in records {
            b.push(op);
            b.extend((content.len() as u64).to_le_bytes());
            b.extend(content);
        }
        if end_magic {
            b.extend(mcap::MAGIC);
        }
        read_all(&b);
    }

    /// Valid MCAP, adversarial values: any type names, garbage or extreme payloads, log times
    /// anywhere in the recorder's range, DROID records with keys missing or garbled.
    #[test]
    fn valid_files_with_arbitrary_values_never_panic(
        messages in prop::collection::vec(message(), 0..24),
        droid in droid_record(),
        finish in any::<bool>(),
    ) {
        let b = adversarial_file(&messages, &droid, finish);
        let o = read_all(&b);
        let tmp = tempfile::tempdir().unwrap();
        recover_dir(tmp.path(), &[&episode().0, &b]);
        let i = o.inspected.as_ref().expect("a file the MCAP library wrote reads");
        prop_assert_eq!(i.complete, finish);
        prop_assert!(i.messages <= messages.len() as u64);
        if finish {
            let (report, _) = o.recovered.as_ref().expect("a finished file recovers");
            prop_assert_eq!(report.messages, messages.len() as u64);
        }
    }
}

// Regression inputs: each a finding of the properties above, kept at its minimal form.

/// A finished file, cut exactly at its end magic and at its footer: still read and recovered.
#[test]
fn an_episode_cut_in_its_footer_still_recovers_every_message() {
    let (bytes, total) = episode();
    for cut in [bytes.len() - 8, bytes.len() - 1, bytes.len() - 20] {
        let o = read_all(&bytes[..cut]);
        let (report, _) = o.recovered.unwrap();
        assert_eq!(report.messages, *total, "cut at {cut}");
    }
}

/// An unfinished file: the magic alone is an empty (not complete) episode, not an error.
#[test]
fn the_magic_alone_reads_as_an_empty_unfinished_episode() {
    let o = read_all(mcap::MAGIC);
    let i = o.inspected.unwrap();
    assert!(!i.complete && i.messages == 0);
    assert!(o.recovered.unwrap_err().contains("no header record survived"));
}

/// Finding (episode/src/inspect.rs, `summarise`): a log time of 2^63 or more (any u64 is a
/// valid MCAP log time) is cast to a negative i64, and `end - start` overflows: a panic in a
/// debug build, a wrong duration in release.
#[test]
#[ignore = "finding: inspect's duration overflows on a log time >= 2^63 (episode/src/inspect.rs, not ours to edit)"]
fn a_log_time_past_i64_does_not_overflow_the_duration() {
    let messages = vec![
        ("std_msgs/msg/String".to_owned(), "/a".to_owned(), u64::MAX, Payload::Bytes(vec![])),
        ("std_msgs/msg/String".to_owned(), "/b".to_owned(), i64::MAX as u64, Payload::Bytes(vec![])),
    ];
    read_all(&adversarial_file(&messages, &BTreeMap::new(), true));
}

/// Finding (episode/src/inspect.rs, `summarise`): step times far apart (a garbled or foreign
/// Step's `timing.step_start`, `capture_ns`) overflow the period, skew and lateness
/// subtractions.
#[test]
#[ignore = "finding: inspect's step period / camera skew overflow on extreme step times (episode/src/inspect.rs, not ours to edit)"]
fn extreme_step_times_do_not_overflow_the_period_or_the_skew() {
    let at = |start: i64, cams: &[i64]| Step {
        timing: ControlTiming { step_start: start, ..Default::default() },
        cameras: cams
            .iter()
            .map(|&t| CameraFrameRef { camera_id: "c".into(), capture_ns: t, ..Default::default() })
            .collect(),
        ..Default::default()
    };
    for steps in [
        vec![at(i64::MIN + 1, &[]), at(i64::MAX, &[])],
        vec![at(1, &[i64::MIN, i64::MAX])],
        vec![at(i64::MAX, &[i64::MIN])],
    ] {
        let messages: Vec<_> = steps
            .into_iter()
            .map(|s| ("labrig_msgs/msg/Step".to_owned(), "/rig/step".to_owned(), T0 as u64, Payload::Step(s)))
            .collect();
        read_all(&adversarial_file(&messages, &BTreeMap::new(), true));
    }
}
