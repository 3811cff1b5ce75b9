//! Zero DDS packets leave loopback: a packet capture (tcpdump, every interface) around a real
//! exchange between labrig and rclpy must show RTPS traffic on 127.0.0.1 and none elsewhere.
//! `.ci/run` runs the same capture around the whole test suite.

use labrig_msgs::geometry_msgs::PoseStamped;
use labrig_msgs::sensor_msgs::JointState;
use labrig_runtime::RosConfig;
use labrig_runtime::ros::{Ros, qos};
use labrig_tests::{Proc, domain_for, rt};
use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// RTPS packets start with the bytes "RTPS" right after the UDP header. BPF's `udp[]` reads
/// IPv4 only, so IPv6 is matched on its own: next header UDP (17) and the payload after the
/// 40-byte IPv6 header and the 8-byte UDP header. `scripts/test.sh` uses the same filter
/// (checked below).
const RTPS_FILTER: &str = "(ip and udp and udp[8:4] = 0x52545053) or (ip6 and ip6[6] = 17 and ip6[48:4] = 0x52545053)";

/// Splits `tcpdump -nn -r` lines into (loopback, elsewhere) by source and destination address.
fn classify(lines: &str) -> (usize, Vec<String>) {
    let mut loopback = 0;
    let mut elsewhere = Vec::new();
    for line in lines.lines() {
        // "... IP 127.0.0.1.7412 > 127.0.0.1.7410: UDP, length 84" (IP6 for IPv6)
        let Some(rest) = line.split_once(" IP ").or_else(|| line.split_once(" IP6 ")).map(|(_, r)| r) else { continue };
        let mut parts = rest.split_whitespace();
        let (src, dst) = (parts.next().unwrap_or(""), parts.nth(1).unwrap_or(""));
        let on_lo = |a: &str| a.starts_with("127.") || a.starts_with("::1.");
        if on_lo(src) && on_lo(dst) {
            loopback += 1;
        } else {
            elsewhere.push(line.to_owned());
        }
    }
    (loopback, elsewhere)
}

#[test]
fn classify_tells_loopback_from_elsewhere() {
    let text = "12:00:00.1 lo In IP 127.0.0.1.7412 > 127.0.0.1.7410: UDP, length 84\n\
                12:00:00.2 eth0 Out IP 10.0.0.5.7412 > 239.255.0.1.7400: UDP, length 84\n";
    let (lo, other) = classify(text);
    assert_eq!(lo, 1);
    assert_eq!(other.len(), 1);
    let text6 = "12:00:00.1 lo In IP6 ::1.7412 > ::1.7410: UDP, length 84\n\
                 12:00:00.2 eth0 Out IP6 fe80::1.7412 > ff02::1.7400: UDP, length 84\n";
    let (lo, other) = classify(text6);
    assert_eq!((lo, other.len()), (1, 1));
}

#[test]
fn the_suite_wide_capture_uses_the_same_filter_and_fails_on_an_empty_capture() {
    let script = std::fs::read_to_string(labrig_tests::repo_root().join("scripts/test.sh")).unwrap();
    assert!(script.contains(&format!("'{RTPS_FILTER}'")), "scripts/test.sh must capture with {RTPS_FILTER:?}");
    assert!(script.contains("saw no RTPS packet"), "scripts/test.sh must fail a capture that saw nothing");
}

#[test]
fn no_dds_packet_leaves_loopback_during_a_labrig_rclpy_exchange() {
    let dir = tempfile::tempdir().unwrap();
    let pcap = dir.path().join("dds.pcap");
    let mut tcpdump = Command::new("tcpdump")
        .args(["-i", "any", "-nn", "-U", "-w"])
        .arg(&pcap)
        .arg(RTPS_FILTER)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("tcpdump must be installed (scripts/setup.sh) and run as root");
    // Wait (bounded) until the capture is running.
    let stderr = tcpdump.stderr.take().unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            let _ = tx.send(line);
        }
    });
    let deadline = Instant::now() + Duration::from_secs(10);
    let mut said = Vec::new();
    while !said.iter().any(|l: &String| l.contains("listening on")) {
        let left = deadline.saturating_duration_since(Instant::now());
        match rx.recv_timeout(left) {
            Ok(line) => said.push(line),
            Err(_) => panic!("tcpdump did not start capturing: {said:?}"),
        }
    }

    // An RTPS-looking datagram over IPv6 loopback: the capture must see IPv6 too (on ::1 only:
    // nothing is sent to any other address).
    let v6 = std::net::UdpSocket::bind("[::1]:0").expect("IPv6 loopback (::1) must be up");
    for _ in 0..3 {
        v6.send_to(b"RTPS\x02\x03\x01\x0f labrig loopback test", "[::1]:7399").unwrap();
    }

    let test = "loopback_capture";
    let domain = domain_for(test);
    let mut listener =
        Proc::ros_peer(domain, &["listen-joint-states", "--topic", "/lo_js", "--count", "20", "--timeout", "30"]);
    listener.wait_json(Duration::from_secs(20), "ready", |v| v["ready"] == true);
    let rt = rt();
    rt.block_on(async {
        let cfg = RosConfig { domain_id: domain, ..RosConfig::default() };
        let mut ros = Ros::new(&cfg, "labrig_loopback").unwrap();
        let publisher = ros.publisher::<JointState>("/lo_js", qos::reliable(100)).unwrap();
        let sub = ros.subscription::<PoseStamped>("/lo_pose", qos::reliable(100)).unwrap();
        let _talker = Proc::ros_peer(domain, &["talk-pose", "--topic", "/lo_pose", "--count", "20", "--rate", "20"]);
        assert!(ros.wait_for_subscribers("/lo_js", 1, Duration::from_secs(20)).await);
        tokio::time::sleep(Duration::from_millis(300)).await;
        for i in 0..20 {
            publisher
                .publish(JointState { position: vec![i as f64], name: vec!["j".into()], ..Default::default() })
                .unwrap();
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        let deadline = Instant::now() + Duration::from_secs(30);
        let mut poses = 0;
        while poses < 20 && Instant::now() < deadline {
            match sub.try_take().unwrap() {
                Some(_) => poses += 1,
                None => tokio::time::sleep(Duration::from_millis(10)).await,
            }
        }
        assert_eq!(poses, 20, "the exchange itself must have happened");
    });
    let done = listener.wait_json(Duration::from_secs(30), "done", |v| v.get("done").is_some());
    assert_eq!(done["received"], 20);
    // Let discovery announcements of the ending participants go out, then stop the capture.
    std::thread::sleep(Duration::from_millis(500));
    let _ = Command::new("kill").args(["-INT", &tcpdump.id().to_string()]).status();
    let _ = tcpdump.wait();
    let read = Command::new("tcpdump").args(["-nn", "-r"]).arg(&pcap).output().unwrap();
    let text = String::from_utf8_lossy(&read.stdout);
    let (loopback, elsewhere) = classify(&text);
    assert!(loopback > 50, "the capture saw only {loopback} RTPS packets on loopback: is it capturing?");
    let ip6 = text.lines().filter(|l| l.contains(" IP6 ::1.") && l.contains("> ::1.7399")).count();
    assert!(ip6 >= 3, "the capture missed the RTPS datagrams sent over IPv6 ({ip6} of 3 seen)");
    assert!(elsewhere.is_empty(), "{} RTPS packets left loopback:\n{}", elsewhere.len(), elsewhere.join("\n"));
}
