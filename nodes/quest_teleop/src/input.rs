//! Where the controller's lines come from, each on a thread of its own feeding the node:
//!
//! - `adb`: `adb [-s <device>] logcat -T 0 -v epoch wE9ryARX:V *:S` (Debian's adb; USB serial,
//!   or `ip:5555` for Wi-Fi, connected first with `adb connect`), optionally starting the
//!   headset app first. When adb exits or the device drops, it is started again after
//!   `reconnect_s`.
//! - `playback`: a recorded logcat file, each line sent at its original time offset (from
//!   the line's own logcat time) scaled by `speed`; lines without a time go out at once;
//!   `repeat` plays it again and again.

use labrig_msgs::Invalid;
use serde::Deserialize;
use std::io::{BufRead, BufReader};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tokio::sync::mpsc::UnboundedSender;

/// The Quest app (FACTS.md).
pub const APP_ACTIVITY: &str = "com.rail.oculus.teleop/com.rail.oculus.teleop.MainActivity";

#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, serde::Serialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum InputKind {
    Adb,
    Playback,
    /// The terminal's keyboard as a virtual controller (sim work without a headset).
    Keyboard,
}

/// `[input]` of the node's config.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct InputConfig {
    pub kind: InputKind,
    /// The adb program.
    pub adb: String,
    /// The headset: a USB serial or `ip:port` (Wi-Fi); empty: adb's only device.
    pub device: String,
    /// Start the headset app over adb before reading.
    pub start_app: bool,
    /// Seconds between adb restarts.
    pub reconnect_s: f64,
    /// Playback: the recorded logcat file.
    pub file: Option<PathBuf>,
    /// Playback: time scale (2.0 = twice as fast).
    pub speed: f64,
    /// Playback: start again at the end (a controller that never leaves; the sim rig).
    pub repeat: bool,
    /// Playback: the node exits a second after the file ends (benchmarks, tests).
    pub exit_at_end: bool,
    /// Keyboard: the controller's move per key press (m) and turn (rad).
    pub keyboard_step_m: f64,
    pub keyboard_step_rad: f64,
    /// Keyboard: readings per second.
    pub keyboard_hz: f64,
}

impl Default for InputConfig {
    fn default() -> Self {
        InputConfig {
            kind: InputKind::Adb,
            adb: "adb".into(),
            device: String::new(),
            start_app: true,
            reconnect_s: 1.0,
            file: None,
            speed: 1.0,
            repeat: false,
            exit_at_end: false,
            keyboard_step_m: 0.005,
            keyboard_step_rad: 0.05,
            keyboard_hz: 50.0,
        }
    }
}

impl InputConfig {
    pub fn validate(&self) -> Result<(), Invalid> {
        if self.kind == InputKind::Playback && self.file.is_none() {
            return Err(Invalid::new("input.file", "input.file: playback needs a recorded logcat file"));
        }
        if !(self.speed.is_finite() && self.speed > 0.0) {
            return Err(Invalid::new("input.speed", format!("input.speed: {} must be positive", self.speed)));
        }
        for (k, v) in [
            ("keyboard_step_m", self.keyboard_step_m),
            ("keyboard_step_rad", self.keyboard_step_rad),
            ("keyboard_hz", self.keyboard_hz),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(Invalid::new(format!("input.{k}"), format!("input.{k}: {v} must be positive")));
            }
        }
        // The input threads sleep 1 / keyboard_hz and reconnect_s: a time a Duration (and an
        // Instant after it) can hold, else the thread panics at start.
        if !(1.0..=1000.0).contains(&self.keyboard_hz) {
            return Err(Invalid::new(
                "input.keyboard_hz",
                format!("input.keyboard_hz: {} must be 1..=1000", self.keyboard_hz),
            ));
        }
        if !(self.reconnect_s.is_finite() && (0.0..=3600.0).contains(&self.reconnect_s)) {
            return Err(Invalid::new(
                "input.reconnect_s",
                format!("input.reconnect_s: {} must be 0..=3600", self.reconnect_s),
            ));
        }
        Ok(())
    }
}

/// What the input thread reports.
#[derive(Debug)]
pub enum InputEvent {
    /// A line and when it was read.
    Line { text: String, read_at: Instant },
    /// A reading made here (the keyboard's virtual controller).
    Reading { reading: Box<crate::logcat::Reading>, read_at: Instant },
    /// The operator asked to quit (Esc / Ctrl-C at the keyboard).
    Quit,
    /// The source's state changed (adb started, lost, ...), for the log and the status.
    Note(String),
    /// The source has no more lines (playback's end).
    End,
}

/// A running input; dropping it stops the thread (and adb).
#[derive(Debug)]
pub struct Input {
    stop: Arc<AtomicBool>,
    child: Arc<Mutex<Option<Child>>>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl Drop for Input {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        if let Ok(mut c) = self.child.lock()
            && let Some(c) = c.as_mut()
        {
            let _ = c.kill();
        }
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// Starts the input `cfg` describes, sending to `tx`; `reorder` is the policy's axis mapping
/// (the keyboard moves its virtual controller along the robot's axes).
pub fn start(
    cfg: &InputConfig,
    tx: UnboundedSender<InputEvent>,
    reorder: nalgebra::Matrix4<f64>,
) -> anyhow::Result<Input> {
    cfg.validate()?;
    let stop = Arc::new(AtomicBool::new(false));
    let child: Arc<Mutex<Option<Child>>> = Arc::new(Mutex::new(None));
    let (cfg2, stop2, child2) = (cfg.clone(), stop.clone(), child.clone());
    let thread = match cfg.kind {
        InputKind::Playback => {
            let path = cfg.file.clone().expect("validated");
            let text =
                std::fs::read_to_string(&path).map_err(|e| anyhow::anyhow!("input.file {}: {e}", path.display()))?;
            std::thread::Builder::new().name("teleop-playback".into()).spawn(move || {
                while playback(&text, cfg2.speed, &tx, &stop2) && cfg2.repeat {}
                let _ = tx.send(InputEvent::End);
            })?
        }
        InputKind::Keyboard => {
            use std::io::IsTerminal;
            anyhow::ensure!(
                std::io::stdin().is_terminal(),
                "input.kind = \"keyboard\" needs a terminal (stdin is not one): run `labrig teleop run --input keyboard` in a shell"
            );
            let vc = crate::keyboard::VirtualController::new(reorder, cfg.keyboard_step_m, cfg.keyboard_step_rad);
            let period = Duration::from_secs_f64(1.0 / cfg.keyboard_hz);
            std::thread::Builder::new()
                .name("teleop-keyboard".into())
                .spawn(move || keyboard(vc, period, &tx, &stop2))?
        }
        InputKind::Adb => {
            std::thread::Builder::new().name("teleop-adb".into()).spawn(move || adb(&cfg2, &tx, &stop2, &child2))?
        }
    };
    Ok(Input { stop, child, thread: Some(thread) })
}

fn sleep_unless_stopped(d: Duration, stop: &AtomicBool) {
    let until = Instant::now() + d;
    while !stop.load(Ordering::SeqCst) {
        let now = Instant::now();
        if now >= until {
            return;
        }
        std::thread::sleep((until - now).min(Duration::from_millis(20)));
    }
}

/// Plays `text` once; false when stopped or the node is gone.
fn playback(text: &str, speed: f64, tx: &UnboundedSender<InputEvent>, stop: &AtomicBool) -> bool {
    // Each line is due its logcat time after the previous timed line; a step back or a jump
    // of more than a minute (the time format changed, a year rolled over) counts as none.
    let mut due = Instant::now();
    let mut prev: Option<i64> = None;
    for line in text.lines() {
        if stop.load(Ordering::SeqCst) {
            return false;
        }
        if let Some(t) = crate::logcat::line_time_ns(line) {
            let step = prev.map_or(0, |p| t.saturating_sub(p));
            prev = Some(t);
            if (0..=60_000_000_000).contains(&step) {
                due += Duration::from_nanos((step as f64 / speed) as u64);
            }
            let now = Instant::now();
            if due > now {
                sleep_unless_stopped(due - now, stop);
            }
        }
        if tx.send(InputEvent::Line { text: line.to_owned(), read_at: Instant::now() }).is_err() {
            return false;
        }
    }
    // One period's pause before a repeat, as between two frames.
    sleep_unless_stopped(Duration::from_millis(14), stop);
    !stop.load(Ordering::SeqCst)
}

fn adb_command(cfg: &InputConfig) -> Command {
    let mut c = Command::new(&cfg.adb);
    if !cfg.device.is_empty() {
        c.args(["-s", &cfg.device]);
    }
    c
}

fn adb(cfg: &InputConfig, tx: &UnboundedSender<InputEvent>, stop: &AtomicBool, child: &Mutex<Option<Child>>) {
    let note = |s: String| {
        let _ = tx.send(InputEvent::Note(s));
    };
    while !stop.load(Ordering::SeqCst) {
        if cfg.device.contains(':') {
            // Wi-Fi: (re)connect first; its output says whether it worked, logcat will tell.
            let _ = Command::new(&cfg.adb)
                .args(["connect", &cfg.device])
                .stdout(Stdio::null())
                .stderr(Stdio::null())
                .status();
        }
        if cfg.start_app {
            let _ = adb_command(cfg)
                .args(["shell", "am", "start", "-n", APP_ACTIVITY])
                .stdout(Stdio::null())
                .stderr(Stdio::null())
                .status();
        }
        let spawned = adb_command(cfg)
            .args(["logcat", "-T", "0", "-v", "epoch", &format!("{}:V", crate::logcat::TAG), "*:S"])
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn();
        let stdout = match spawned {
            Ok(mut c) => {
                let out = c.stdout.take();
                if let Ok(mut slot) = child.lock() {
                    // A stop that came while adb was starting: the drop has already looked
                    // for a child to kill.
                    if stop.load(Ordering::SeqCst) {
                        let _ = c.kill();
                        let _ = c.wait();
                        return;
                    }
                    *slot = Some(c);
                }
                note(format!(
                    "adb logcat started ({})",
                    if cfg.device.is_empty() { "the one device" } else { &cfg.device }
                ));
                out
            }
            Err(e) => {
                note(format!("cannot run {} ({e}): install Debian's adb", cfg.adb));
                None
            }
        };
        if let Some(out) = stdout {
            for line in BufReader::new(out).lines() {
                let Ok(line) = line else { break };
                if tx.send(InputEvent::Line { text: line, read_at: Instant::now() }).is_err() {
                    return;
                }
                if stop.load(Ordering::SeqCst) {
                    break;
                }
            }
        }
        let status = child.lock().ok().and_then(|mut c| c.take()).map(|mut c| {
            let _ = c.kill();
            c.wait()
        });
        if stop.load(Ordering::SeqCst) {
            return;
        }
        note(format!(
            "adb logcat ended ({}); reconnecting in {:.1} s",
            match status {
                Some(Ok(s)) => s.to_string(),
                Some(Err(e)) => e.to_string(),
                None => "not started".into(),
            },
            cfg.reconnect_s
        ));
        sleep_unless_stopped(Duration::from_secs_f64(cfg.reconnect_s), stop);
    }
}

/// Restores the terminal when the keyboard thread ends, however it ends.
struct RawMode;
impl Drop for RawMode {
    fn drop(&mut self) {
        let _ = crossterm::terminal::disable_raw_mode();
    }
}

fn keyboard(
    mut vc: crate::keyboard::VirtualController,
    period: Duration,
    tx: &UnboundedSender<InputEvent>,
    stop: &AtomicBool,
) {
    use crate::keyboard::KeyEffect;
    use crossterm::event::{Event, KeyCode, KeyEventKind, KeyModifiers};
    if let Err(e) = crossterm::terminal::enable_raw_mode() {
        let _ = tx.send(InputEvent::Note(format!("keyboard: cannot switch the terminal to raw mode: {e}")));
        let _ = tx.send(InputEvent::End);
        return;
    }
    let _raw = RawMode;
    eprint!(
        "keyboard controller: space = grip (deadman, toggles), w/s a/d r/f = x y z, q/e = turn, g = gripper, 1 = success, 2 = failure, Esc = quit\r\n"
    );
    let mut next = Instant::now();
    while !stop.load(Ordering::SeqCst) {
        let wait = next.saturating_duration_since(Instant::now());
        if crossterm::event::poll(wait).unwrap_or(false) {
            if let Ok(Event::Key(k)) = crossterm::event::read()
                && k.kind != KeyEventKind::Release
            {
                let quit_keys = matches!(k.code, KeyCode::Esc)
                    || (k.code == KeyCode::Char('c') && k.modifiers.contains(KeyModifiers::CONTROL));
                let effect = match k.code {
                    _ if quit_keys => KeyEffect::Quit,
                    KeyCode::Char(c) => vc.key(c),
                    _ => KeyEffect::Ignored,
                };
                if effect == KeyEffect::Quit {
                    let _ = tx.send(InputEvent::Quit);
                    return;
                }
            }
            continue;
        }
        next += period;
        if tx.send(InputEvent::Reading { reading: Box::new(vc.reading()), read_at: Instant::now() }).is_err() {
            return;
        }
    }
}
