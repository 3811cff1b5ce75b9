//! Bad input never panics: the Quest logcat parser (`parse_line`, `payload`, `line_time_ns`,
//! `LineStats`) on arbitrary text, on logcat-shaped garbage and on mangled good lines; and
//! good lines round-trip: any reading, written in any of adb's three line forms, parses back
//! to itself, and any logcat time parses to its nanoseconds.

use labrig_quest_teleop::logcat::{
    Hand, LineError, LineStats, Reading, TAG, line_time_ns, parse_line, parse_payload, payload,
};
use nalgebra::Matrix4;
use proptest::prelude::*;

/// `n` cases; failures are reported with their minimal input, not persisted (a regression
/// worth keeping becomes a named test below).
fn cases(n: u32) -> ProptestConfig {
    ProptestConfig { cases: n, failure_persistence: None, ..ProptestConfig::default() }
}

/// Every parser on `line`: no panic, and the counts agree with the parse.
fn parse_everything(line: &str) -> Result<Reading, LineError> {
    let _ = line_time_ns(line);
    let parsed = parse_line(line);
    if let Ok(p) = payload(line) {
        assert_eq!(parse_payload(p), parsed, "parse_line is payload + parse_payload");
    }
    let mut stats = LineStats::default();
    let taken = stats.take(line);
    assert_eq!(stats.readings + stats.other + stats.bad, 1);
    match (&parsed, taken) {
        (Ok(r), Some(Ok(t))) => assert_eq!(*r, t),
        (Err(LineError::OtherTag), None) => {}
        (Err(e), Some(Err(t))) => assert_eq!(*e, t),
        (p, t) => panic!("parse_line gave {p:?}, LineStats::take {t:?}"),
    }
    parsed
}

fn finite() -> impl Strategy<Value = f64> {
    prop_oneof![
        3 => -10.0f64..10.0,
        1 => any::<f64>().prop_filter("finite", |v| v.is_finite()),
        1 => Just(0.0),
        1 => Just(-0.0),
    ]
}

fn hand() -> impl Strategy<Value = Hand> {
    (
        // A Vec, not an array: sixteen unions' value trees inline overflow a test thread's stack.
        prop::option::of(prop::collection::vec(finite(), 16)),
        prop::array::uniform8(any::<bool>()),
        (finite(), finite(), finite(), finite()),
    )
        .prop_map(|(pose, b, (grip, trigger, jx, jy))| Hand {
            pose: pose.map(|v| Matrix4::from_row_slice(&v)),
            present: b[0],
            grip_pressed: b[1],
            grip,
            trigger,
            joystick: [jx, jy],
            joystick_pressed: b[2],
            success: b[3],
            failure: b[4],
            thumb_up: b[5],
            trigger_pressed: b[6],
        })
}

fn reading() -> impl Strategy<Value = Reading> {
    (hand(), hand()).prop_map(|(right, left)| Reading { right, left })
}

/// The app's payload for `r` (FACTS.md's format), the two sides in either order.
fn payload_of(r: &Reading, left_first: bool) -> String {
    let pose = |side: &str, h: &Hand| {
        h.pose.map(|m| {
            let v: Vec<String> = (0..4).flat_map(|i| (0..4).map(move |j| (i, j))).map(|ij| m[ij].to_string()).collect();
            format!("{side}:{}", v.join(" "))
        })
    };
    let mut sides: Vec<String> = [pose("r", &r.right), pose("l", &r.left)].into_iter().flatten().collect();
    if left_first {
        sides.reverse();
    }
    let mut buttons = Vec::new();
    for (side, h, names) in [
        ("right", &r.right, ["R", "A", "B", "RThU", "RJ", "RG", "RTr"]),
        ("left", &r.left, ["L", "X", "Y", "LThU", "LJ", "LG", "LTr"]),
    ] {
        let flags =
            [h.present, h.success, h.failure, h.thumb_up, h.joystick_pressed, h.grip_pressed, h.trigger_pressed];
        buttons.extend(names.iter().zip(flags).filter(|(_, on)| *on).map(|(n, _)| n.to_string()));
        buttons.push(format!("{side}JS {} {}", h.joystick[0], h.joystick[1]));
        buttons.push(format!("{side}Grip {}", h.grip));
        buttons.push(format!("{side}Trig {}", h.trigger));
    }
    format!("{}&{}", sides.join("|"), buttons.join(","))
}

/// adb logcat's three line forms around a payload.
fn line_of(form: u8, payload: &str) -> String {
    match form % 3 {
        0 => format!("11-21 23:40:01.123  4521  4587 I {TAG}: {payload}"),
        1 => format!("1763768401.123  4521  4587 I {TAG}: {payload}"),
        _ => format!("I/{TAG}( 4521): {payload}"),
    }
}

/// Text made of what logcat lines are made of: digits, the separators, the tag, button names.
fn logcat_ish() -> impl Strategy<Value = String> {
    let token = prop_oneof![
        Just(TAG.to_owned()),
        Just(format!("{TAG}: ")),
        Just(format!("I/{TAG}(")),
        Just("):".to_owned()),
        "[&|:, ().\\-]",
        "[rlRLABXYJGT]{1,4}",
        "(right|left)(JS|Grip|Trig)",
        "-?[0-9]{1,20}(\\.[0-9]{0,12})?(e-?[0-9]{1,3})?",
        "(NaN|inf|-inf|1e999)",
        " {1,3}",
        "[\\r\\n\\t\\x00]",
        "\\PC",
    ];
    prop::collection::vec(token, 0..60).prop_map(|t| t.concat())
}

/// One edit of a line: cut, insert, replace or drop characters somewhere.
#[derive(Debug, Clone)]
enum Edit {
    Cut(prop::sample::Index),
    Insert(prop::sample::Index, String),
    Replace(prop::sample::Index, char),
    Delete(prop::sample::Index, usize),
    Double(prop::sample::Index, usize),
}

fn edit() -> impl Strategy<Value = Edit> {
    prop_oneof![
        any::<prop::sample::Index>().prop_map(Edit::Cut),
        (any::<prop::sample::Index>(), prop_oneof!["[&|:, .\\-0-9rlRLe]{1,4}", Just(TAG.to_owned()), "\\PC{1,3}"])
            .prop_map(|(i, s)| Edit::Insert(i, s)),
        (
            any::<prop::sample::Index>(),
            prop_oneof![Just('&'), Just('|'), Just(':'), Just(','), Just(' '), any::<char>()]
        )
            .prop_map(|(i, c)| Edit::Replace(i, c)),
        (any::<prop::sample::Index>(), 1usize..20).prop_map(|(i, n)| Edit::Delete(i, n)),
        (any::<prop::sample::Index>(), 1usize..40).prop_map(|(i, n)| Edit::Double(i, n)),
    ]
}

fn apply(line: &str, edits: &[Edit]) -> String {
    let mut c: Vec<char> = line.chars().collect();
    for e in edits {
        let at = |i: &prop::sample::Index, c: &Vec<char>| i.index(c.len() + 1);
        match e {
            Edit::Cut(i) => c.truncate(at(i, &c)),
            Edit::Insert(i, s) => {
                let k = at(i, &c);
                c.splice(k..k, s.chars());
            }
            Edit::Replace(i, ch) => {
                if !c.is_empty() {
                    let k = i.index(c.len());
                    c[k] = *ch;
                }
            }
            Edit::Delete(i, n) => {
                let k = at(i, &c);
                c.drain(k..(k + n).min(c.len()));
            }
            Edit::Double(i, n) => {
                let k = at(i, &c);
                let part: Vec<char> = c[k..(k + n).min(c.len())].to_vec();
                c.splice(k..k, part);
            }
        }
    }
    c.into_iter().collect()
}

proptest! {
    #![proptest_config(cases(512))]

    /// Any text at all: a reading or an error value.
    #[test]
    fn arbitrary_text_never_panics(s in any::<String>()) {
        let _ = parse_everything(&s);
        let _ = parse_everything(&line_of(0, &s));
        let _ = parse_everything(&line_of(2, &s));
    }

    /// Text made of logcat's own pieces reaches deeper into the parser than random text.
    #[test]
    fn logcat_shaped_garbage_never_panics(s in logcat_ish(), form in any::<u8>()) {
        let _ = parse_everything(&s);
        let _ = parse_everything(&line_of(form, &s));
    }

    /// Any reading, in any of the three line forms, parses back to itself.
    #[test]
    fn a_reading_written_as_a_line_parses_back(r in reading(), form in any::<u8>(), left_first in any::<bool>()) {
        let line = line_of(form, &payload_of(&r, left_first));
        prop_assert_eq!(parse_everything(&line), Ok(r), "{}", line);
    }

    /// A good line cut, spliced, doubled or with characters replaced: never a panic.
    #[test]
    fn a_mangled_good_line_never_panics(r in reading(), form in any::<u8>(), edits in prop::collection::vec(edit(), 1..6)) {
        let line = line_of(form, &payload_of(&r, false));
        let _ = parse_everything(&apply(&line, &edits));
    }

    /// Logcat's times parse to their nanoseconds: threadtime on a 31-day month grid, epoch
    /// seconds as they are.
    #[test]
    fn logcat_times_parse_to_their_nanoseconds(
        (month, day, h, m, s) in (1i64..=12, 1i64..=31, 0i64..=23, 0i64..=59, 0i64..=59),
        frac in "[0-9]{1,9}",
        secs in 100_000_000i64..=9_000_000_000,
    ) {
        let frac_ns = frac.parse::<i64>().unwrap() * 10i64.pow(9 - frac.len() as u32);
        let threadtime = format!("{month:02}-{day:02} {h:02}:{m:02}:{s:02}.{frac}  1 2 I {TAG}: x");
        let day_index = (month - 1) * 31 + (day - 1);
        prop_assert_eq!(line_time_ns(&threadtime), Some((((day_index * 24 + h) * 60 + m) * 60 + s) * 1_000_000_000 + frac_ns));
        let epoch = format!("{secs}.{frac}  1 2 I {TAG}: x");
        prop_assert_eq!(line_time_ns(&epoch), Some(secs * 1_000_000_000 + frac_ns));
    }

    /// Any numbers (signs, huge, overlong) in a time's fields, beside good ones: a time or
    /// none, never a panic.
    #[test]
    fn any_numbers_in_a_time_never_panic(f in prop::collection::vec(time_field(), 6)) {
        let _ = line_time_ns(&format!("{}-{} {}:{}:{}.{} x", f[0], f[1], f[2], f[3], f[4], f[5]));
        let _ = line_time_ns(&format!("{}.{} x", f[0], f[5]));
        let _ = line_time_ns(&format!("{}{}{}{}.{} x", f[0], f[1], f[2], f[3], f[5]));
    }
}

/// A number as a logcat time field might hold one: a plausible value, an extreme, or anything
/// signed and overlong.
fn time_field() -> impl Strategy<Value = String> {
    prop_oneof![
        (1u32..=12).prop_map(|v| format!("{v:02}")),
        Just(i64::MIN.to_string()),
        Just(i64::MAX.to_string()),
        "[+\\-]?[0-9]{0,22}",
    ]
}

/// A threadtime clock with a negative hour passed the range check (only `h > 23` was checked)
/// and `i64::MIN` hours overflowed the nanosecond arithmetic: a panic on one line of a
/// recorded trace. Now no time, as for any other malformed clock.
#[test]
fn a_negative_hour_in_a_logcat_time_is_no_time_not_an_overflow() {
    assert_eq!(line_time_ns("01-01 -9223372036854775808:00:00.0 x"), None);
    assert_eq!(line_time_ns("01-01 00:-9223372036854775808:00.0 x"), None);
    assert_eq!(line_time_ns("01-01 00:00:-9223372036854775808.0 x"), None);
    assert_eq!(line_time_ns("01-01 -1:00:00.0 x"), None);
}
