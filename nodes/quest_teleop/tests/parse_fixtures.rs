//! The parser on the committed logcat fixtures (tests/fixtures/make_traces.py writes them from
//! the documented line format).

use labrig_quest_teleop::logcat::{LineStats, line_time_ns};

fn fixture(name: &str) -> String {
    std::fs::read_to_string(std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures").join(name)).unwrap()
}

#[test]
fn a_mixed_stream_is_counted_line_by_line() {
    let mut s = LineStats::default();
    let mut readings = Vec::new();
    for l in fixture("mixed.logcat").lines() {
        if let Some(Ok(r)) = s.take(l) {
            readings.push(r);
        }
    }
    // 6 app lines, 3 lines of adb and other apps, 3 bad (cut in half, two run together,
    // garbage): nothing lost, nothing invented.
    assert_eq!((s.readings, s.other, s.bad), (6, 3, 3), "{s:?}");
    assert!(readings[0].right.grip_pressed && readings[0].left.present);
    assert_eq!(readings[0].right.joystick, [0.1, -0.2]);
    assert_eq!(readings[4].right.pose, None, "a side with 3 numbers is dropped, the line kept");
}

#[test]
fn the_square_trace_is_72_hz_with_the_documented_presses() {
    let text = fixture("square.logcat");
    let mut s = LineStats::default();
    let mut times = Vec::new();
    let mut grip_changes = 0;
    let mut last_grip = false;
    let mut a_presses = 0;
    let mut last_a = false;
    for l in text.lines() {
        let r = s.take(l).unwrap().unwrap();
        times.push(line_time_ns(l).unwrap());
        grip_changes += usize::from(r.right.grip_pressed != last_grip);
        last_grip = r.right.grip_pressed;
        a_presses += usize::from(r.right.success && !last_a);
        last_a = r.right.success;
    }
    assert_eq!(s.bad, 0);
    assert_eq!(grip_changes, 3, "pressed, released, pressed");
    assert_eq!(a_presses, 1);
    let span = (times.last().unwrap() - times[0]) as f64 / 1e9;
    assert!((span - 8.5).abs() < 0.01, "{span}");
    assert!(times.windows(2).all(|w| w[1] >= w[0]));
}

/// Playing a file whose lines switch time format (threadtime, then epoch: 55 years apart)
/// sends every line instead of sleeping to the far one (nextest ends a hung test after 5 min).
#[test]
fn playback_of_a_file_mixing_time_formats_sends_every_line() {
    use labrig_quest_teleop::input::{InputConfig, InputEvent, InputKind, start};
    let (tx, mut rx) = tokio::sync::mpsc::unbounded_channel();
    let file = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/mixed.logcat");
    let cfg = InputConfig { kind: InputKind::Playback, file: Some(file), ..InputConfig::default() };
    let _input = start(&cfg, tx, labrig_quest_teleop::policy::reorder_matrix(&[-2, -1, -3, 4])).unwrap();
    let mut lines = 0;
    loop {
        match rx.blocking_recv() {
            Some(InputEvent::Line { .. }) => lines += 1,
            Some(InputEvent::End) | None => break,
            Some(_) => {}
        }
    }
    assert_eq!(lines, 12);
}
