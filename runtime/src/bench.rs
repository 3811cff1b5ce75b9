//! What the benchmarks beside each node share: a process's CPU time from /proc and the
//! percentile summary every latency figure is printed as.

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

/// p50, p99, max and count of `values` as JSON, the keys suffixed with `unit`
/// (`{"p50_us": .., "p99_us": .., "max_us": .., "n": ..}`); null when there are none.
pub fn summary(mut values: Vec<f64>, unit: &str) -> serde_json::Value {
    if values.is_empty() {
        return serde_json::Value::Null;
    }
    values.sort_by(f64::total_cmp);
    let p = |q: f64| values[((values.len() - 1) as f64 * q).round() as usize];
    let mut m = serde_json::Map::new();
    for (name, q) in [("p50", 0.5), ("p99", 0.99), ("max", 1.0)] {
        m.insert(format!("{name}_{unit}"), p(q).into());
    }
    m.insert("n".into(), values.len().into());
    serde_json::Value::Object(m)
}

#[cfg(test)]
mod tests {
    #[test]
    fn a_summary_names_its_unit_and_takes_nearest_ranks() {
        let v: Vec<f64> = (1..=100).rev().map(f64::from).collect();
        let s = super::summary(v, "ms");
        assert_eq!(
            (s["p50_ms"].as_f64(), s["p99_ms"].as_f64(), s["max_ms"].as_f64()),
            (Some(51.0), Some(99.0), Some(100.0))
        );
        assert_eq!(s["n"], 100);
        assert!(super::summary(vec![], "us").is_null());
    }
}
