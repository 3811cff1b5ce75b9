//! What the benchmarks beside each node share: a process's CPU time and holdings from /proc,
//! the percentile summary every latency figure is printed as, and the growth rate of a
//! quantity sampled over time (a soak's verdict).

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

/// What a process holds at one moment, from /proc: resident memory, open file descriptors,
/// threads, and the CPU seconds it has used so far.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ProcSample {
    pub rss_bytes: u64,
    pub fds: u32,
    pub threads: u32,
    pub cpu_s: f64,
}

/// A sample of process `pid` (`/proc/<pid>/status`, `/proc/<pid>/fd`, `/proc/<pid>/stat`); None
/// when it is gone or unreadable.
pub fn sample_of(pid: u32) -> Option<ProcSample> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let field = |name: &str| {
        status.lines().find_map(|l| l.strip_prefix(name)).and_then(|v| v.split_whitespace().next()?.parse::<u64>().ok())
    };
    let rss_kb = field("VmRSS:")?;
    let threads = u32::try_from(field("Threads:")?).ok()?;
    let fds = u32::try_from(std::fs::read_dir(format!("/proc/{pid}/fd")).ok()?.count()).ok()?;
    let cpu_s = cpu_seconds_of(&pid.to_string())?;
    Some(ProcSample { rss_bytes: rss_kb * 1024, fds, threads, cpu_s })
}

/// The least-squares slope of `points` (x, y): y's change per unit of x. None with fewer than
/// two distinct x.
pub fn slope(points: &[(f64, f64)]) -> Option<f64> {
    let n = points.len() as f64;
    let (mx, my) = points.iter().fold((0.0, 0.0), |(a, b), (x, y)| (a + x / n, b + y / n));
    let sxx: f64 = points.iter().map(|(x, _)| (x - mx).powi(2)).sum();
    let sxy: f64 = points.iter().map(|(x, y)| (x - mx) * (y - my)).sum();
    (points.len() >= 2 && sxx > 0.0).then(|| sxy / sxx)
}

/// The growth per hour of a quantity sampled at `(seconds since the start, value)`, fitted on
/// the samples after `warmup_s` (a process fills its caches and pools first); None with fewer
/// than two samples after it.
pub fn growth_per_hour(samples: &[(f64, f64)], warmup_s: f64) -> Option<f64> {
    let after: Vec<(f64, f64)> = samples.iter().copied().filter(|(t, _)| *t >= warmup_s).collect();
    slope(&after).map(|per_s| per_s * 3600.0)
}

#[cfg(test)]
mod tests {
    #[test]
    fn a_planted_growth_is_measured_and_the_warmup_left_out() {
        // 1 MB every 10 s after a 60 s warm-up that jumped by 50 MB: 360 MB/h, not more.
        let mb = 1e6;
        let samples: Vec<(f64, f64)> = (0..60)
            .map(|k| {
                let t = f64::from(k) * 10.0;
                let v = if t < 60.0 { t / 60.0 * 50.0 * mb } else { 50.0 * mb + (t - 60.0) / 10.0 * mb };
                (t, v)
            })
            .collect();
        let g = super::growth_per_hour(&samples, 60.0).unwrap();
        assert!((g - 360.0 * mb).abs() < 1e-3, "{g}");
        // Flat after the warm-up: no growth.
        let flat: Vec<(f64, f64)> = (0..20).map(|k| (f64::from(k), if k < 5 { f64::from(k) } else { 9.0 })).collect();
        assert_eq!(super::growth_per_hour(&flat, 5.0), Some(0.0));
        assert_eq!(super::growth_per_hour(&flat, 100.0), None);
        assert_eq!(super::slope(&[(1.0, 2.0), (1.0, 3.0)]), None);
    }

    #[test]
    fn a_process_sample_sees_descriptors_opened() {
        let pid = std::process::id();
        let before = super::sample_of(pid).unwrap();
        assert!(before.rss_bytes > 1_000_000 && before.threads >= 1 && before.cpu_s >= 0.0, "{before:?}");
        let dir = tempfile::tempdir().unwrap();
        let files: Vec<std::fs::File> =
            (0..10).map(|k| std::fs::File::create(dir.path().join(k.to_string())).unwrap()).collect();
        let after = super::sample_of(pid).unwrap();
        assert!(after.fds >= before.fds + 10, "{before:?} -> {after:?}");
        drop(files);
        assert!(super::sample_of(u32::MAX).is_none());
    }

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
