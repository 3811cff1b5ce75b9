//! Bad input never panics: the episode reader (`inspect`, `read_episode`), `recover` and
//! `recover_in_place` (`labrig recover`) on truncated, bit-flipped and overwritten episode
//! files, on an episode whose second part is damaged, on arbitrary bytes (with and without
//! MCAP's magic), on well-framed records of arbitrary content, and on well-formed files whose
//! values are arbitrary (log times, step timings, garbage payloads of known types).
//!
//! Each property: no panic; a file is either read (damage reported in the inspection) or a
//! typed error naming the file. A truncated file recovers into one that `inspect` reads as
//! complete, holding no more messages than the original. Each finding (a chunk record that
//! claimed an exabyte and aborted the process in mcap's `ChunkReader`, overflows on extreme
//! times and counts, a damaged finished part left unreadable) is a named regression test at
//! the end, with its minimal input.

use labrig_episode::bag::Reliability;
use labrig_episode::recover::recover;
use labrig_episode::{EpisodeMetadata, EpisodeWriter, ReadError, RigIdentity, inspect, read_episode};
use labrig_msgs::Nanos;
use labrig_msgs::rig::{CameraFrameRef, ControlTiming, RobotState, Step};
use labrig_msgs::sensor_msgs::CompressedImage;
use labrig_msgs::std_msgs::Header;
use proptest::prelude::*;
use std::collections::BTreeMap;
use std::path::Path;
use std::sync::OnceLock;

/// `n` cases; failures are reported with their minimal input, not persisted (a regression
/// worth keeping becomes a named test below).
fn cases(n: u32) -> ProptestConfig {
    ProptestConfig { cases: n, failure_persistence: None, ..ProptestConfig::default() }
}

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

/// The byte ranges of `bytes` holding chunks' compressed records. Damage there once aborted
/// the process (`a_chunk_record_claiming_an_exabyte_is_damage_not_an_abort`): the properties
/// using this damage everything else (the header, chunk headers, metadata, attachments,
/// indexes, the summary, the footer); `bit_flips_inside_chunks_never_abort` damages the
/// chunk bodies.
fn chunk_bodies(bytes: &[u8]) -> Vec<std::ops::Range<usize>> {
    let u64_at = |i: usize| u64::from_le_bytes(bytes[i..i + 8].try_into().unwrap()) as usize;
    let mut ranges = Vec::new();
    let mut i = 8;
    while i + 9 <= bytes.len() {
        let (op, len) = (bytes[i], u64_at(i + 1));
        if op == 0x06 {
            // start, end, uncompressed size (u64 each), crc (u32), compression (string), size.
            let name_at = i + 9 + 28;
            let data_at =
                name_at + 4 + u32::from_le_bytes(bytes[name_at..name_at + 4].try_into().unwrap()) as usize + 8;
            ranges.push(data_at..data_at + u64_at(data_at - 8));
        }
        i += 9 + len;
    }
    ranges
}

/// A position in `bytes` outside every chunk body.
fn outside_chunks(bytes: &[u8], at: prop::sample::Index) -> usize {
    let bodies = chunk_bodies(bytes);
    let mut allowed: Vec<std::ops::Range<usize>> = Vec::new();
    let mut from = 0;
    for r in &bodies {
        allowed.push(from..r.start);
        from = r.end;
    }
    allowed.push(from..bytes.len());
    let total: usize = allowed.iter().map(|r| r.len()).sum();
    let mut k = at.index(total);
    for r in allowed {
        if k < r.len() {
            return r.start + k;
        }
        k -= r.len();
    }
    unreachable!()
}

/// What the readers make of `bytes`, written as an episode file.
struct Outcome {
    inspected: Result<labrig_episode::Inspection, ReadError>,
    recovered: Result<(labrig_episode::recover::RecoverReport, labrig_episode::Inspection), String>,
}

/// Runs every reader on `bytes` (as a file, and as the one part of a directory) and checks
/// what holds for any input: no panic; errors name the file; a recovered file reads back
/// complete with the messages recover reported. (`labrig recover` on a directory,
/// [`recover_dir`], where the property says so: it copies and fsyncs once more.)
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
        Ok(_) => match inspect(&dir) {
            Ok(after) => {
                assert!(after.complete, "{:?}", after.flags);
                assert!(dir.join("metadata.yaml").is_file());
                if let Ok(before) = &before {
                    assert!(after.messages <= before.messages, "recovery invented messages");
                }
                let _ = read_episode(&dir);
            }
            // A part with a summary is left as it is, even when it does not read (the finding
            // `a_finished_part_with_a_damaged_start_is_not_left_unreadable`); recovery must
            // never make a readable directory unreadable.
            Err(e) => assert!(before.is_err(), "recovery made a readable episode unreadable: {e}"),
        },
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
/// `a_log_time_past_i64_does_not_overflow_the_bag_duration` for the rest of u64's range.
fn log_time() -> impl Strategy<Value = u64> {
    prop_oneof![Just(0u64), Just(i64::MAX as u64), 0u64..=i64::MAX as u64, (T0 as u64)..(T0 as u64 + 10 * TICK as u64)]
}

/// Step times: ordinary ones near T0 and large ones (the extremes whose differences once
/// overflowed are `extreme_step_times_do_not_overflow_the_period_or_the_skew`).
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
    Step(Box<Step>),
    Image(i32, Vec<u8>),
}

fn message() -> impl Strategy<Value = (String, String, u64, Payload)> {
    let payload = prop_oneof![
        prop::collection::vec(any::<u8>(), 0..64).prop_map(Payload::Bytes),
        // A valid encapsulation header and a body of any bytes.
        prop::collection::vec(any::<u8>(), 0..64).prop_map(|b| Payload::Bytes([vec![0, 1, 0, 0], b].concat())),
        step().prop_map(|s| Payload::Step(Box::new(s))),
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
            Payload::Step(s) => labrig_msgs::encode(s.as_ref()).unwrap_or_default(),
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
    #![proptest_config(cases(64))]

    /// Cut anywhere: the readers read up to the cut; recover gives a complete file with at
    /// most the original's messages, whenever the header survived.
    #[test]
    fn a_truncated_episode_reads_up_to_the_cut_and_recovers(at in any::<prop::sample::Index>()) {
        let (bytes, total) = episode();
        let cut = at.index(bytes.len() + 1);
        let o = read_all(&bytes[..cut]);
        recover_dir(tempfile::tempdir().unwrap().path(), &[&bytes[..cut]]);
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

    /// Bits flipped anywhere outside the chunks' compressed records (see [`chunk_bodies`]):
    /// read or refused, never a panic.
    #[test]
    fn a_bit_flipped_episode_never_panics(flips in prop::collection::vec((any::<prop::sample::Index>(), 0u8..8), 1..8)) {
        let (bytes, _) = episode();
        let mut b = bytes.clone();
        for (at, bit) in flips {
            b[outside_chunks(bytes, at)] ^= 1 << bit;
        }
        read_all(&b);
        recover_dir(tempfile::tempdir().unwrap().path(), &[&b]);
    }

    /// An episode recorded in two parts (a recorder restart), the second one cut and damaged:
    /// the directory reads and recovers, or the error names it.
    #[test]
    fn a_damaged_second_part_never_panics(
        at in any::<prop::sample::Index>(),
        flips in prop::collection::vec((any::<prop::sample::Index>(), 0u8..8), 0..4),
    ) {
        let (bytes, _) = episode();
        let mut b = bytes.clone();
        for (at, bit) in flips {
            b[outside_chunks(bytes, at)] ^= 1 << bit;
        }
        b.truncate(at.index(bytes.len() + 1));
        let tmp = tempfile::tempdir().unwrap();
        recover_dir(tmp.path(), &[bytes, &b]);
    }

    /// A byte range overwritten with anything (a torn write, another file's blocks).
    #[test]
    fn an_overwritten_range_never_panics(at in any::<prop::sample::Index>(), junk in prop::collection::vec(any::<u8>(), 1..256), cut in any::<bool>()) {
        let (bytes, _) = episode();
        let mut b = bytes.clone();
        let start = outside_chunks(bytes, at);
        let end = (start + junk.len()).min(b.len());
        let end = chunk_bodies(bytes).iter().filter(|r| r.start >= start).map(|r| r.start).fold(end, usize::min);
        b[start..end].copy_from_slice(&junk[..end - start]);
        if cut {
            b.truncate(end);
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

proptest! {
    #![proptest_config(cases(256))]

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

/// Finding (episode/src/recover.rs + bag.rs, work in progress): any u64 is a valid MCAP log
/// time; `recover` casts it to i64 (2^64 - 1 becomes -1), and the rosbag2 duration
/// (`BagInfo::duration_ns`, `end_ns - start_ns`) overflows: a panic in a debug build, a wrong
/// duration in release.
#[test]
fn a_log_time_past_i64_does_not_overflow_the_bag_duration() {
    let messages = vec![
        ("std_msgs/msg/String".to_owned(), "/a".to_owned(), u64::MAX, Payload::Bytes(vec![])),
        ("std_msgs/msg/String".to_owned(), "/b".to_owned(), i64::MAX as u64, Payload::Bytes(vec![])),
    ];
    read_all(&adversarial_file(&messages, &BTreeMap::new(), true));
}

/// Writes `parts` as the parts of one episode directory and reads it.
fn read_parts(parts: &[Vec<u8>]) {
    let tmp = tempfile::tempdir().unwrap();
    let bytes: Vec<&[u8]> = parts.iter().map(Vec::as_slice).collect();
    for (k, b) in bytes.iter().enumerate() {
        std::fs::write(tmp.path().join(format!("episode_{k}.mcap")), b).unwrap();
    }
    let _ = inspect(tmp.path());
    let _ = read_episode(tmp.path());
    recover_dir(tmp.path(), &bytes);
}

fn steps_at(log: u64, indices: &[u64]) -> Vec<(String, String, u64, Payload)> {
    indices
        .iter()
        .map(|&i| {
            let s = Step { step_index: i, ..Default::default() };
            ("labrig_msgs/msg/Step".to_owned(), "/rig/step".to_owned(), log, Payload::Step(Box::new(s)))
        })
        .collect()
}

/// Finding (episode/src/inspect.rs, `gaps`, work in progress): the steps missing between two
/// parts are `first.saturating_sub(last + 1)`; a part whose last step index is u64::MAX (a
/// garbled or foreign Step) overflows `last + 1`.
#[test]
fn a_part_ending_at_step_u64_max_does_not_overflow_the_gap() {
    let none = BTreeMap::new();
    read_parts(&[
        adversarial_file(&steps_at(T0 as u64, &[u64::MAX]), &none, true),
        adversarial_file(&steps_at(T0 as u64, &[0]), &none, true),
    ]);
}

/// Finding (episode/src/inspect.rs, `gaps`, work in progress): the seconds between two parts
/// are `next.start_ns - previous.end_ns` on log times cast to i64; a part logged at i64::MAX
/// before one logged at 2^63 (cast: i64::MIN) overflows.
#[test]
fn parts_logged_far_apart_do_not_overflow_the_gap() {
    let none = BTreeMap::new();
    read_parts(&[
        adversarial_file(&steps_at(i64::MAX as u64, &[0]), &none, true),
        adversarial_file(&steps_at(1 << 63, &[1]), &none, true),
    ]);
}

/// Finding (episode/src/inspect.rs, `summarise`): step times far apart (a garbled or foreign
/// Step's `timing.step_start`, `capture_ns`) overflow the period, skew and lateness
/// subtractions.
#[test]
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
            .map(|s| ("labrig_msgs/msg/Step".to_owned(), "/rig/step".to_owned(), T0 as u64, Payload::Step(Box::new(s))))
            .collect();
        read_all(&adversarial_file(&messages, &BTreeMap::new(), true));
    }
}

/// A minimal MCAP: magic, a header record, then one zstd chunk holding `records` (as a zstd
/// frame of one raw block: no compressor needed), the chunk's CRC left at 0 (unchecked).
fn file_with_zstd_chunk(records: &[u8]) -> Vec<u8> {
    let record = |op: u8, body: &[u8]| [&[op][..], &(body.len() as u64).to_le_bytes(), body].concat();
    let string = |s: &str| [&(s.len() as u32).to_le_bytes()[..], s.as_bytes()].concat();
    assert!(records.len() < 256, "one-byte frame content size");
    let block_header = (1 | ((records.len() as u32) << 3)).to_le_bytes();
    let frame = [&[0x28, 0xB5, 0x2F, 0xFD, 0x20, records.len() as u8][..], &block_header[..3], records].concat();
    let chunk = [
        &T0.to_le_bytes()[..],
        &T0.to_le_bytes(),
        &(records.len() as u64).to_le_bytes(),
        &0u32.to_le_bytes(),
        &string("zstd"),
        &(frame.len() as u64).to_le_bytes(),
        &frame,
    ]
    .concat();
    [mcap::MAGIC, &record(0x01, &[string("ros2"), string("x")].concat()), &record(0x06, &chunk)].concat()
}

/// The control for the finding below: the hand-made zstd chunk reads, its record is counted.
#[test]
fn a_hand_made_zstd_chunk_reads() {
    // A schema record: id 1, empty name, encoding and data.
    let records = [&[0x03u8][..], &14u64.to_le_bytes(), &1u16.to_le_bytes(), &[0; 12]].concat();
    let o = read_all(&file_with_zstd_chunk(&records));
    let i = o.inspected.unwrap();
    assert_eq!((i.messages, i.damage), (0, None));
    assert_eq!(o.recovered.unwrap().0.chunks, 1);
}

/// Finding (episode/src/inspect.rs and recover.rs through mcap 0.26's `ChunkReader`): a record
/// length inside a decompressed chunk is trusted and allocated before the chunk's CRC is
/// checked (the `ChunkReader` sets no `record_length_limit`), so one flipped byte in a chunk (a zstd raw literal) makes `inspect`,
/// `read_episode`, `recover` and `labrig export droid` abort the whole process ("memory
/// allocation of 8676466157105982985 bytes failed", SIGABRT): no panic to catch, no error.
/// Run alone (it aborts the test binary until fixed).
#[test]
fn a_chunk_record_claiming_an_exabyte_is_damage_not_an_abort() {
    // 2^60 bytes: "memory allocation failed", SIGABRT; 2^63 and more: "capacity overflow", a panic.
    let records = [&[0x05u8][..], &(1u64 << 60).to_le_bytes(), &[0; 16]].concat();
    let o = read_all(&file_with_zstd_chunk(&records));
    assert!(o.inspected.unwrap().damage.is_some());
}

/// Finding (episode/src/recover.rs, `recover_in_place`, work in progress): a part counts as
/// finished when `mcap::Summary::read` finds a summary, which reads from the footer backwards
/// and never looks at the start; a finished episode whose first byte was flipped is then "left
/// as it is", `labrig recover` succeeds, and `inspect` still refuses the directory (not an MCAP
/// file). Minimal input: bit 0 of byte 0. Either outcome is right: recovered, or refused by
/// name.
#[test]
fn a_finished_part_with_a_damaged_start_is_not_left_unreadable() {
    let mut b = episode().0.clone();
    b[0] ^= 1;
    let tmp = tempfile::tempdir().unwrap();
    std::fs::write(tmp.path().join("episode_0.mcap"), &b).unwrap();
    match labrig_episode::recover::recover_in_place(tmp.path()) {
        Ok(_) => drop(inspect(tmp.path()).expect("after `labrig recover` succeeded, the episode reads")),
        Err(e) => assert!(e.to_string().contains("episode_0.mcap"), "{e}"),
    }
}

proptest! {
    #![proptest_config(cases(64))]

    /// Bits flipped anywhere, chunk bodies included: the abort of
    /// `a_chunk_record_claiming_an_exabyte_is_damage_not_an_abort` within a few dozen cases.
    #[test]
    fn bit_flips_inside_chunks_never_abort(flips in prop::collection::vec((any::<prop::sample::Index>(), 0u8..8), 1..8)) {
        let (bytes, _) = episode();
        let mut b = bytes.clone();
        for (at, bit) in flips {
            let i = at.index(b.len());
            b[i] ^= 1 << bit;
        }
        read_all(&b);
    }
}

/// Finding (episode/src/bag.rs, `BagInfo::single` / `message_count` / `merged`, work in
/// progress): `recover_in_place` takes a finished part's message counts from its summary's
/// statistics (`mcap::Summary::read` does not check the summary's CRC) and sums them
/// unchecked; a summary whose channel counts read u64::MAX (flipped bits) overflows the sum.
#[test]
fn summary_counts_past_u64_do_not_overflow_the_bag() {
    let mut b = episode().0.clone();
    let u64_at = |b: &[u8], i: usize| u64::from_le_bytes(b[i..i + 8].try_into().unwrap()) as usize;
    // The statistics record (opcode 0x0B) in the summary, then its channel message counts:
    // after message count, schema, channel, attachment, metadata and chunk counts, two times.
    let mut i = 8;
    while b[i] != 0x0B {
        i += 9 + u64_at(&b, i + 1);
    }
    let map_at = i + 9 + 8 + 2 + 4 + 4 + 4 + 4 + 8 + 8;
    let entries = u32::from_le_bytes(b[map_at..map_at + 4].try_into().unwrap()) as usize / 10;
    for k in 0..entries {
        let at = map_at + 4 + k * 10 + 2;
        b[at..at + 8].copy_from_slice(&u64::MAX.to_le_bytes());
    }
    let tmp = tempfile::tempdir().unwrap();
    std::fs::write(tmp.path().join("episode_0.mcap"), &b).unwrap();
    let _ = labrig_episode::recover::recover_in_place(tmp.path());
}
