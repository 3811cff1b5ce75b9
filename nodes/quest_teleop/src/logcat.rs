//! The Quest app's logcat lines (FACTS.md, "Quest input"): `com.rail.oculus.teleop` logs one
//! line per rendered frame with tag `wE9ryARX`; the payload after `wE9ryARX: ` is
//! `<transforms>&<buttons>`:
//!
//! - transforms: `|`-separated `r:<16 floats>` / `l:<16 floats>`, space-separated, the
//!   controller's 4x4 pose (row-major) in head coordinates; a side with other than 16 numbers
//!   is dropped;
//! - buttons: comma-separated tokens: `R` / `L` (which hands are present), a boolean button by
//!   name while pressed (right: A, B, RThU, RJ, RG, RTr; left: X, Y, LThU, LJ, LG, LTr), an
//!   analog value as `name v1 [v2]` (rightJS x y, rightGrip, rightTrig, left*).
//!
//! Lines come from `adb logcat` in its default `threadtime` form
//! (`11-21 23:40:01.123  1234  5678 I wE9ryARX: ...`), `-v epoch` (`1763768401.123 ...`), or
//! `brief` (`I/wE9ryARX( 1234): ...`). Anything else — other tags, garbage, a line cut in
//! half, two lines run together — is an error value, never a panic.

use nalgebra::Matrix4;
use std::collections::BTreeMap;

/// The app's logcat tag.
pub const TAG: &str = "wE9ryARX";

/// One controller's reading.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Hand {
    /// The pose in head coordinates, where the line had one.
    pub pose: Option<Matrix4<f64>>,
    /// A present in the button list (`R` / `L`).
    pub present: bool,
    /// Grip button pressed (`RG` / `LG`): DROID's deadman.
    pub grip_pressed: bool,
    pub grip: f64,
    pub trigger: f64,
    pub joystick: [f64; 2],
    /// Joystick pressed (`RJ` / `LJ`): redefines forward.
    pub joystick_pressed: bool,
    /// A (right) / X (left).
    pub success: bool,
    /// B (right) / Y (left).
    pub failure: bool,
    pub thumb_up: bool,
    pub trigger_pressed: bool,
}

/// Both controllers of one line.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Reading {
    pub right: Hand,
    pub left: Hand,
}

impl Reading {
    pub fn hand(&self, right: bool) -> &Hand {
        if right { &self.right } else { &self.left }
    }
}

/// Why a line was not a reading.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum LineError {
    #[error("not the app's line (no `{TAG}: ` tag)")]
    OtherTag,
    #[error("no `&` between transforms and buttons")]
    NoSeparator,
    #[error("more than one `{TAG}` payload on the line (lines run together)")]
    Interleaved,
    #[error("button `{0}`: {1}")]
    Button(String, String),
    #[error("transform `{0}`: {1}")]
    Transform(String, String),
}

/// A line's time as logcat printed it, ns: since the epoch (`-v epoch`) or since the start of
/// the year (`threadtime`, which prints no year); only differences within a file matter.
pub fn line_time_ns(line: &str) -> Option<i64> {
    let mut words = line.split_whitespace();
    let first = words.next()?;
    if let Some((s, frac)) = first.split_once('.')
        && !first.contains('-')
        && s.len() >= 9
    {
        let secs: i64 = s.parse().ok()?;
        return secs.checked_mul(1_000_000_000)?.checked_add(frac_ns(frac)?);
    }
    // threadtime: MM-DD HH:MM:SS.mmm
    let (month, day) = first.split_once('-')?;
    let (month, day): (i64, i64) = (month.parse().ok()?, day.parse().ok()?);
    if !(1..=12).contains(&month) || !(1..=31).contains(&day) {
        return None;
    }
    let clock = words.next()?;
    let (hms, frac) = clock.split_once('.')?;
    let mut parts = hms.split(':').map(|p| p.parse::<i64>().ok());
    let (h, m, s) = (parts.next()??, parts.next()??, parts.next()??);
    // Signed fields parse too ("-5"): bound both ends, else i64::MIN hours overflow below.
    if parts.next().is_some() || !(0..=23).contains(&h) || !(0..=59).contains(&m) || !(0..=60).contains(&s) {
        return None;
    }
    // Day of the year through a 31-day month grid: monotonic within a year, which is all
    // playback needs.
    let day_index = (month - 1) * 31 + (day - 1);
    Some((((day_index * 24 + h) * 60 + m) * 60 + s) * 1_000_000_000 + frac_ns(frac)?)
}

fn frac_ns(frac: &str) -> Option<i64> {
    if frac.is_empty() || frac.len() > 9 || !frac.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    Some(frac.parse::<i64>().ok()? * 10i64.pow(9 - frac.len() as u32))
}

/// The payload of an app line: the text after `wE9ryARX: ` (or `wE9ryARX(pid): ` in brief).
pub fn payload(line: &str) -> Result<&str, LineError> {
    let at = line.find(TAG).ok_or(LineError::OtherTag)?;
    let rest = &line[at + TAG.len()..];
    let rest = match rest.strip_prefix('(') {
        // brief: I/wE9ryARX( 1234): payload
        Some(r) => r.split_once("):").map(|(_, p)| p).ok_or(LineError::OtherTag)?,
        None => rest.strip_prefix(':').ok_or(LineError::OtherTag)?,
    };
    let p = rest.strip_prefix(' ').unwrap_or(rest).trim_end_matches(['\r', '\n']);
    if p.contains(TAG) {
        return Err(LineError::Interleaved);
    }
    Ok(p)
}

/// Parses an app line into both controllers' reading.
pub fn parse_line(line: &str) -> Result<Reading, LineError> {
    parse_payload(payload(line)?)
}

/// Why a value in a line is not a number: the text says which.
struct BadNumber(String);

fn numbers(text: &str) -> Result<Vec<f64>, BadNumber> {
    text.split(' ')
        .filter(|t| !t.is_empty())
        .map(|t| match t.parse::<f64>() {
            Ok(v) if v.is_finite() => Ok(v),
            Ok(_) => Err(BadNumber(format!("{t} is not finite"))),
            Err(_) => Err(BadNumber(format!("{t:?} is not a number"))),
        })
        .collect()
}

/// Parses `<transforms>&<buttons>`.
pub fn parse_payload(payload: &str) -> Result<Reading, LineError> {
    let (transforms, buttons) = payload.split_once('&').ok_or(LineError::NoSeparator)?;
    let mut r = Reading::default();
    for part in transforms.split('|').map(str::trim).filter(|p| !p.is_empty()) {
        let (side, values) =
            part.split_once(':').ok_or_else(|| LineError::Transform(short(part), "no `side:`".into()))?;
        let hand = match side.trim() {
            "r" => &mut r.right,
            "l" => &mut r.left,
            other => return Err(LineError::Transform(short(part), format!("unknown side {other:?}"))),
        };
        let v = numbers(values).map_err(|BadNumber(e)| LineError::Transform(short(part), e))?;
        // A side with other than 16 numbers is dropped (as the app's own reader does).
        if v.len() == 16 {
            hand.pose = Some(Matrix4::from_row_slice(&v));
        }
    }
    let mut analog: BTreeMap<&str, Vec<f64>> = BTreeMap::new();
    for token in buttons.split(',').map(str::trim).filter(|t| !t.is_empty()) {
        let (name, values) = token.split_once(' ').unwrap_or((token, ""));
        if values.is_empty() {
            let flag = match name {
                "R" => &mut r.right.present,
                "L" => &mut r.left.present,
                "A" => &mut r.right.success,
                "B" => &mut r.right.failure,
                "RThU" => &mut r.right.thumb_up,
                "RJ" => &mut r.right.joystick_pressed,
                "RG" => &mut r.right.grip_pressed,
                "RTr" => &mut r.right.trigger_pressed,
                "X" => &mut r.left.success,
                "Y" => &mut r.left.failure,
                "LThU" => &mut r.left.thumb_up,
                "LJ" => &mut r.left.joystick_pressed,
                "LG" => &mut r.left.grip_pressed,
                "LTr" => &mut r.left.trigger_pressed,
                other => return Err(LineError::Button(short(other), "unknown button".into())),
            };
            *flag = true;
        } else {
            let v = numbers(values).map_err(|BadNumber(e)| LineError::Button(short(name), e))?;
            analog.insert(name, v);
        }
    }
    for (name, v) in analog {
        let (hand, what) = match name.strip_prefix("right") {
            Some(w) => (&mut r.right, w),
            None => match name.strip_prefix("left") {
                Some(w) => (&mut r.left, w),
                None => return Err(LineError::Button(short(name), "unknown analog value".into())),
            },
        };
        let need = if what == "JS" { 2 } else { 1 };
        if v.len() != need {
            return Err(LineError::Button(short(name), format!("{} values, expected {need}", v.len())));
        }
        match what {
            "JS" => hand.joystick = [v[0], v[1]],
            "Grip" => hand.grip = v[0],
            "Trig" => hand.trigger = v[0],
            _ => return Err(LineError::Button(short(name), "unknown analog value".into())),
        }
    }
    Ok(r)
}

fn short(s: &str) -> String {
    s.chars().take(40).collect()
}

/// Counts of what a stream of lines held.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct LineStats {
    pub readings: u64,
    /// Lines of other tags (adb's own output, other apps): skipped, not errors.
    pub other: u64,
    /// App lines that did not parse.
    pub bad: u64,
}

impl LineStats {
    /// Notes one line's outcome; returns the reading, if any.
    pub fn take(&mut self, line: &str) -> Option<Result<Reading, LineError>> {
        match parse_line(line) {
            Ok(r) => {
                self.readings += 1;
                Some(Ok(r))
            }
            Err(LineError::OtherTag) => {
                self.other += 1;
                None
            }
            Err(e) => {
                self.bad += 1;
                Some(Err(e))
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const IDENTITY: &str = "1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1";

    fn line(payload: &str) -> String {
        format!("11-21 23:40:01.123  4521  4587 I {TAG}: {payload}")
    }

    #[test]
    fn a_full_line_gives_both_controllers() {
        let p = format!(
            "r:1 0 0 0.1 0 1 0 0.2 0 0 1 0.3 0 0 0 1|l:{IDENTITY}&R,L,A,RG,RJ,rightJS 0.25 -0.5,rightGrip 1.0,rightTrig 0.75,leftJS 0.0 0.0,leftGrip 0.0,leftTrig 0.0"
        );
        let r = parse_line(&line(&p)).unwrap();
        let pose = r.right.pose.unwrap();
        assert_eq!((pose[(0, 3)], pose[(1, 3)], pose[(2, 3)]), (0.1, 0.2, 0.3), "row-major translation column");
        assert!(r.right.present && r.left.present);
        assert!(r.right.success && r.right.grip_pressed && r.right.joystick_pressed);
        assert!(!r.right.failure && !r.left.grip_pressed);
        assert_eq!(r.right.joystick, [0.25, -0.5]);
        assert_eq!((r.right.grip, r.right.trigger), (1.0, 0.75));
        assert_eq!(r.left.pose, Some(Matrix4::identity()));
    }

    #[test]
    fn every_logcat_format_and_its_time() {
        let p = format!("r:{IDENTITY}&R");
        for l in [
            format!("11-21 23:40:01.123  4521  4587 I {TAG}: {p}"),
            format!("1763768401.123  4521  4587 I {TAG}: {p}"),
            format!("I/{TAG}( 4521): {p}"),
        ] {
            assert!(parse_line(&l).unwrap().right.present, "{l}");
        }
        assert_eq!(line_time_ns(&format!("1763768401.123  4521  4587 I {TAG}: x")), Some(1_763_768_401_123_000_000));
        let a = line_time_ns("11-21 23:40:01.123  1 2 I x").unwrap();
        let b = line_time_ns("11-21 23:40:02.100  1 2 I x").unwrap();
        assert_eq!(b - a, 977_000_000);
        assert_eq!(line_time_ns("garbage"), None);
        assert_eq!(line_time_ns("13-40 25:99:99.1 x"), None);
        assert_eq!(line_time_ns("99999999999999.0 x"), None, "overflow is no time, not a panic");
    }

    #[test]
    fn a_side_without_16_numbers_is_dropped() {
        let r = parse_line(&line("r:1 0 0&R")).unwrap();
        assert_eq!(r.right.pose, None);
        assert!(r.right.present);
    }

    #[test]
    fn bad_lines_are_named_errors() {
        assert_eq!(parse_line("--------- beginning of main"), Err(LineError::OtherTag));
        assert_eq!(parse_line(&line("r:1 0 0 0")), Err(LineError::NoSeparator), "cut before the buttons");
        let e = parse_line(&line(&format!("r:{IDENTITY}&R,rightTrig abc"))).unwrap_err();
        assert_eq!(e, LineError::Button("rightTrig".into(), "\"abc\" is not a number".into()));
        let e = parse_line(&line(&format!("r:{IDENTITY}&R,rightJS 0.5"))).unwrap_err();
        assert!(e.to_string().contains("1 values, expected 2"), "{e}");
        let e = parse_line(&line("r:1 0 0 NaN 0 1 0 0 0 0 1 0 0 0 0 1&R")).unwrap_err();
        assert!(matches!(e, LineError::Transform(_, ref m) if m.contains("not finite")), "{e}");
        let two = format!("{}{}", line(&format!("r:{IDENTITY}&R")), line("x&R"));
        assert_eq!(parse_line(&two), Err(LineError::Interleaved));
        let e = parse_line(&line(&format!("q:{IDENTITY}&R"))).unwrap_err();
        assert!(e.to_string().contains("unknown side"), "{e}");
    }

    #[test]
    fn stats_count_readings_other_lines_and_bad_ones() {
        let mut s = LineStats::default();
        for l in [line(&format!("r:{IDENTITY}&R")), "adb: device offline".into(), line("garbage")] {
            s.take(&l);
        }
        assert_eq!(s, LineStats { readings: 1, other: 1, bad: 1 });
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(2000))]
        /// Any text, and any mangling of a good line (cut, spliced, bytes replaced), parses
        /// or errs: never a panic.
        #[test]
        fn never_panics_on_any_text(s in ".{0,300}") {
            let _ = parse_line(&s);
            let _ = line_time_ns(&s);
            let _ = parse_line(&format!("01-01 00:00:00.000 1 1 I {TAG}: {s}"));
        }

        #[test]
        fn never_panics_on_a_mangled_good_line(cut in 0usize..400, at in 0usize..400, junk in "[ -~]{0,8}") {
            let good = line(&format!("r:{IDENTITY}|l:{IDENTITY}&R,L,RG,rightJS 0.1 0.2,rightGrip 1.0,rightTrig 0.5"));
            let cut = cut.min(good.len());
            let at = at.min(cut);
            let mut bad = good[..cut].to_owned();
            if bad.is_char_boundary(at) {
                bad.insert_str(at, &junk);
            }
            let _ = parse_line(&bad);
        }
    }
}
