//! CPU time from /proc, for the benchmarks beside each node (one reader for all of them).

/// CPU seconds (user + system) a process has used, from `/proc/<proc>/stat` (`proc`: a pid,
/// or `self`); None when it is gone or unreadable.
pub fn cpu_seconds_of(proc: &str) -> Option<f64> {
    let stat = std::fs::read_to_string(format!("/proc/{proc}/stat")).ok()?;
    // Fields after the command name (which may hold spaces and parentheses) start at field 3
    // (state); utime is field 14, stime 15.
    let fields: Vec<&str> = stat.rsplit_once(')')?.1.split_whitespace().collect();
    let ticks = |i: usize| fields.get(i - 3).and_then(|f| f.parse::<f64>().ok());
    // USER_HZ is 100 on every Linux labrig runs on.
    Some((ticks(14)? + ticks(15)?) / 100.0)
}

/// CPU seconds this process has used (NaN if /proc cannot say).
pub fn process_cpu_seconds() -> f64 {
    cpu_seconds_of("self").unwrap_or(f64::NAN)
}
