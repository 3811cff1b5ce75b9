//! Tests run in parallel, each rig on its own DDS domain. A test gets its domain only through
//! `domain_for` / `domains_for`, which read the one registry `TEST_DOMAINS` and panic on a key
//! missing from it; these tests check the registry itself: no two keys, no two domains, no
//! domain a labrig command uses by default, and no test that names a domain number instead.

use labrig_tests::{DEFAULT_DOMAINS, TEST_DOMAINS, domain_for, domains_for, repo_root};
use std::collections::BTreeMap;

/// Every (key, domain) pair of the registry, ranges expanded.
fn claimed() -> Vec<(&'static str, u16)> {
    TEST_DOMAINS.iter().flat_map(|&(key, first, count)| (first..first + count).map(move |d| (key, d))).collect()
}

#[test]
fn every_registered_key_has_domains_of_its_own() {
    assert!(TEST_DOMAINS.len() > 50, "the registry lists only {} keys", TEST_DOMAINS.len());
    let mut keys = BTreeMap::new();
    for &(key, _, count) in TEST_DOMAINS {
        assert!(count >= 1, "`{key}` registers no domain");
        assert!(keys.insert(key, ()).is_none(), "`{key}` is registered twice");
    }
    let mut owner: BTreeMap<u16, &str> = BTreeMap::new();
    for (key, d) in claimed() {
        // Fast DDS / the RTPS port mapping (7400 + 250 x domain) allow 0..=232.
        assert!(d <= 232, "`{key}`: domain {d} is past the RTPS port range (0..=232)");
        if let Some(other) = owner.insert(d, key) {
            panic!("domain {d} is claimed by both `{other}` and `{key}`");
        }
        assert!(
            !DEFAULT_DOMAINS.iter().any(|r| r.contains(&d)),
            "`{key}`: domain {d} is one a labrig command uses by default ({DEFAULT_DOMAINS:?})"
        );
    }
}

#[test]
fn a_key_missing_from_the_registry_is_refused_by_name() {
    let err = std::panic::catch_unwind(|| domain_for("no_such_test_key")).unwrap_err();
    let msg = err.downcast_ref::<String>().cloned().unwrap_or_default();
    assert!(msg.contains("no_such_test_key") && msg.contains("TEST_DOMAINS"), "{msg}");
    // A key with several domains is handed out whole only by domains_for.
    let (first, count) = domains_for("fault_bench_recorder_kill");
    assert!(count > 1 && first > 0);
    assert!(std::panic::catch_unwind(|| domain_for("fault_bench_recorder_kill")).is_err());
}

/// The registry is the only door: a test that passes a domain number itself (a literal after
/// `--domain-id`, in `ROS_DOMAIN_ID` or a `domain_id:` field) goes around it. The one literal
/// allowed is cli.rs' 300, a domain the CLI must refuse.
#[test]
fn no_test_names_a_domain_number_itself() {
    let dir = repo_root().join("tests/tests");
    let mut files = 0;
    let mut found = Vec::new();
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_none_or(|e| e != "rs") || path.ends_with("domains.rs") {
            continue;
        }
        files += 1;
        let text = std::fs::read_to_string(&path).unwrap();
        for (n, line) in text.lines().enumerate() {
            for marker in ["\"--domain-id\", \"", "\"ROS_DOMAIN_ID\", \"", "domain_id: "] {
                if let Some(i) = line.find(marker) {
                    let rest = &line[i + marker.len()..];
                    let number: String = rest.chars().take_while(|c| c.is_ascii_digit()).collect();
                    if !number.is_empty() && number != "300" {
                        found.push(format!("{}:{}: {}", path.display(), n + 1, line.trim()));
                    }
                }
            }
        }
    }
    assert!(files > 10, "read only {files} test files");
    assert!(found.is_empty(), "tests naming a DDS domain number instead of TEST_DOMAINS:\n{}", found.join("\n"));
}
