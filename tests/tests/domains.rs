//! Tests run two at a time, each on its own DDS domain from `domain_for(key)`. Two keys that
//! hash to the same domain make two tests see each other's nodes (it happened: the recorder
//! test and the lockstep test shared domain 78 and the lockstep run stalled). This checks
//! every literal key in tests/tests/*.rs.

use labrig_tests::{domain_for, repo_root};
use std::collections::BTreeMap;

#[test]
fn every_test_key_gets_its_own_domain() {
    let mut keys: BTreeMap<u16, Vec<String>> = BTreeMap::new();
    let dir = repo_root().join("tests/tests");
    let mut files = 0;
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_none_or(|e| e != "rs") {
            continue;
        }
        files += 1;
        let text = std::fs::read_to_string(&path).unwrap();
        for marker in ["domain_for(\"", "lockstep_run(\""] {
            for (i, _) in text.match_indices(marker) {
                let rest = &text[i + marker.len()..];
                let key = &rest[..rest.find('"').unwrap()];
                keys.entry(domain_for(key)).or_default().push(key.to_owned());
            }
        }
    }
    assert!(files > 5 && keys.len() > 10, "found {} keys in {files} files", keys.len());
    let clashes: Vec<_> = keys
        .iter()
        .filter(|(_, k)| {
            let mut k = (*k).clone();
            k.sort();
            k.dedup();
            k.len() > 1
        })
        .collect();
    assert!(clashes.is_empty(), "test keys sharing a DDS domain: {clashes:?}");
}
