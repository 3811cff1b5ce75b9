//! The documentation works when followed literally: every labrig command a guide shows (a
//! line of a ```sh / ```bash / ```console block starting with `labrig` or
//! `./scripts/labrig`) is one the CLI accepts, judged by the programs' own parsers
//! (`LABRIG_PARSE_ONLY=1`: parse, exit, run nothing); every relative link and `#anchor` in
//! README.md, ARCHITECTURE.md and docs/ resolves; the mdBook builds.

use labrig_tests::{cache_dir, labrig_bin, output_text, repo_root, workspace_bin};
use std::collections::BTreeSet;
use std::path::PathBuf;
use std::process::Command;

/// The Markdown files the checks cover.
fn pages() -> Vec<PathBuf> {
    let root = repo_root();
    let mut out = vec![root.join("README.md"), root.join("ARCHITECTURE.md"), root.join("launch_configs/README.md")];
    let mut docs: Vec<PathBuf> = std::fs::read_dir(root.join("docs"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "md"))
        .collect();
    docs.sort();
    out.extend(docs);
    out
}

/// Numbered lines (1-based).
type Lines = Vec<(usize, String)>;

/// Each fenced block's language and lines, and the text outside the blocks.
fn split(text: &str) -> (Vec<(String, Lines)>, Lines) {
    let (mut blocks, mut prose) = (Vec::new(), Vec::new());
    let mut open: Option<(String, Lines)> = None;
    for (i, line) in text.lines().enumerate() {
        let fence = line.trim_start().starts_with("```");
        match (&mut open, fence) {
            (None, true) => open = Some((line.trim_start().trim_start_matches('`').trim().to_owned(), Vec::new())),
            (Some(_), true) => blocks.push(open.take().unwrap()),
            (Some((_, lines)), false) => lines.push((i + 1, line.to_owned())),
            (None, false) => prose.push((i + 1, line.to_owned())),
        }
    }
    (blocks, prose)
}

/// The labrig command lines of shell blocks: (line number, the arguments after `labrig`).
fn commands(text: &str) -> Vec<(usize, String, Vec<String>)> {
    let (blocks, _) = split(text);
    let mut out = Vec::new();
    for (lang, lines) in blocks {
        if !matches!(lang.as_str(), "sh" | "bash" | "console" | "shell") {
            continue;
        }
        let mut joined: Lines = Vec::new();
        let mut carry: Option<(usize, String)> = None;
        for (n, line) in lines {
            let (start, mut acc) = carry.take().unwrap_or((n, String::new()));
            acc.push_str(line.trim_end());
            if acc.ends_with('\\') {
                acc.pop();
                acc.push(' ');
                carry = Some((start, acc));
            } else {
                joined.push((start, acc));
            }
        }
        for (n, line) in joined {
            let line = line.trim().trim_start_matches("$ ").trim().to_owned();
            let rest = match line.strip_prefix("./scripts/labrig ").or_else(|| line.strip_prefix("labrig ")) {
                Some(r) => r,
                None => continue,
            };
            // Placeholders become one word; then what follows a pipe, a redirect, a comment
            // or another command is not labrig's.
            let mut s = String::new();
            let mut in_angle = false;
            for c in rest.chars() {
                match c {
                    '<' if !in_angle => {
                        in_angle = true;
                        s.push_str("PLACEHOLDER");
                    }
                    '>' if in_angle => in_angle = false,
                    _ if in_angle => {}
                    _ => s.push(c),
                }
            }
            for cut in [" | ", " |", " > ", " >> ", " 2>", " &&", " ||", ";", " # ", " &"] {
                if let Some(i) = s.find(cut) {
                    s.truncate(i);
                }
            }
            let Some(words) = shlex::split(&s) else {
                out.push((n, line.clone(), vec!["<unbalanced quotes>".into()]));
                continue;
            };
            let words: Vec<String> =
                words.into_iter().map(|w| if w.contains('$') { "PLACEHOLDER".to_owned() } else { w }).collect();
            out.push((n, line, words));
        }
    }
    out
}

#[test]
fn every_command_the_guides_show_is_one_the_cli_accepts() {
    // Every program a labrig command hands its arguments to, built (lone runs lack some).
    for (bin, package) in [
        ("labrig-sim", "labrig-sim-bridge"),
        ("labrig-calibrate", "labrig-calibration"),
        ("labrig-dataset", "labrig-dataset"),
        ("labrig-droid", "labrig-droid"),
        ("labrig-policies", "labrig-policies"),
        ("labrig-policy", "labrig-policy-server"),
        ("labrig-franka", "labrig-franka"),
        ("labrig-gripper", "labrig-gripper"),
        ("labrig-cameras", "labrig-cameras"),
        ("labrig-control", "labrig-control"),
        ("labrig-recorder", "labrig-recorder"),
        ("labrig-teleop", "labrig-quest-teleop"),
        ("labrig-station", "labrig-station"),
        ("labrig-doctor", "labrig-doctor"),
    ] {
        workspace_bin(bin, package);
    }
    let labrig = labrig_bin();
    let mut checked = 0;
    let mut refused = Vec::new();
    for page in pages() {
        let text = std::fs::read_to_string(&page).unwrap();
        for (n, line, args) in commands(&text) {
            let out = Command::new(&labrig)
                .args(&args)
                .env("LABRIG_PARSE_ONLY", "1")
                .current_dir(repo_root())
                .output()
                .unwrap();
            checked += 1;
            if !out.status.success() {
                let why = String::from_utf8_lossy(&out.stderr)
                    .lines()
                    .find(|l| !l.trim().is_empty())
                    .unwrap_or("")
                    .to_owned();
                refused.push(format!("{}:{n}: `{line}`: {why}", page.strip_prefix(repo_root()).unwrap().display()));
            }
        }
    }
    assert!(checked > 100, "only {checked} commands found: the extraction is broken");
    assert!(
        refused.is_empty(),
        "{} of {checked} commands are refused by the CLI:\n{}",
        refused.len(),
        refused.join("\n")
    );
}

/// The check itself: a made-up flag, a made-up subcommand and a missing argument are refused.
#[test]
fn the_command_check_refuses_what_the_cli_refuses() {
    let labrig = labrig_bin();
    let parses = |args: &[&str]| {
        let out = Command::new(&labrig).args(args).env("LABRIG_PARSE_ONLY", "1").output().unwrap();
        out.status.success()
    };
    workspace_bin("labrig-gripper", "labrig-gripper");
    workspace_bin("labrig-doctor", "labrig-doctor");
    assert!(parses(&["doctor", "--rig", "x.toml", "--json"]));
    assert!(!parses(&["doctor", "--no-such-flag"]));
    assert!(!parses(&["no-such-command"]));
    assert!(parses(&["gripper", "run", "--port", "/dev/ttyUSB0"]));
    assert!(!parses(&["gripper", "run", "--no-such-flag"]), "a forwarded command is judged by its program");
    assert!(!parses(&["inspect"]), "inspect needs its episode");
    // And nothing ran: `labrig demo` parses in well under the time it takes to start a rig.
    let episodes = tempfile::tempdir().unwrap();
    assert!(parses(&["demo", "--out", episodes.path().to_str().unwrap()]));
    assert_eq!(std::fs::read_dir(episodes.path()).unwrap().count(), 0, "the demo ran");
    let cmds =
        commands("```sh\n$ labrig replay <episode> --sim \\\n    --json | jq .\nlabrig inspect $EP # note\n```\n");
    assert_eq!(
        cmds.iter().map(|c| c.2.clone()).collect::<Vec<_>>(),
        [vec!["replay", "PLACEHOLDER", "--sim", "--json"], vec!["inspect", "PLACEHOLDER"]]
    );
}

/// GitHub's heading anchors: lowercase, spaces to '-', other punctuation but '-' and '_' gone;
/// a repeated heading gets -1, -2, ...
fn anchors(text: &str) -> BTreeSet<String> {
    let (_, prose) = split(text);
    let mut seen = BTreeSet::new();
    for (_, line) in prose {
        let Some(title) = line.strip_prefix('#').map(|t| t.trim_start_matches('#')) else { continue };
        if !title.starts_with(' ') {
            continue;
        }
        let slug: String = title
            .trim()
            .to_lowercase()
            .chars()
            .filter_map(|c| match c {
                ' ' => Some('-'),
                c if c.is_alphanumeric() || c == '-' || c == '_' => Some(c),
                _ => None,
            })
            .collect();
        let mut s = slug.clone();
        let mut k = 0;
        while seen.contains(&s) {
            k += 1;
            s = format!("{slug}-{k}");
        }
        seen.insert(s);
    }
    seen
}

/// The links of the text outside code: `[text](target)`, inline code skipped.
fn links(text: &str) -> Vec<(usize, String)> {
    let (_, prose) = split(text);
    let mut out = Vec::new();
    for (n, line) in prose {
        // Inline code spans are not links.
        let mut plain = String::new();
        for (i, part) in line.split('`').enumerate() {
            if i % 2 == 0 {
                plain.push_str(part);
            }
        }
        let mut rest = plain.as_str();
        while let Some(i) = rest.find("](") {
            let after = &rest[i + 2..];
            let Some(end) = after.find(')') else { break };
            let target = after[..end].split_whitespace().next().unwrap_or("").to_owned();
            out.push((n, target));
            rest = &after[end..];
        }
    }
    out
}

#[test]
fn every_link_in_the_docs_resolves() {
    let mut broken = Vec::new();
    let mut checked = 0;
    for page in pages() {
        let text = std::fs::read_to_string(&page).unwrap();
        let dir = page.parent().unwrap();
        for (n, target) in links(&text) {
            if target.starts_with("http://") || target.starts_with("https://") || target.starts_with("mailto:") {
                continue;
            }
            checked += 1;
            let (path, anchor) = target.split_once('#').unwrap_or((target.as_str(), ""));
            let file = if path.is_empty() { page.clone() } else { dir.join(path) };
            let at = format!("{}:{n}: ({target})", page.strip_prefix(repo_root()).unwrap().display());
            if !file.exists() {
                broken.push(format!("{at}: no such file"));
                continue;
            }
            if !anchor.is_empty() {
                if file.extension().is_none_or(|e| e != "md") {
                    broken.push(format!("{at}: an anchor into a file that is not Markdown"));
                } else if !anchors(&std::fs::read_to_string(&file).unwrap()).contains(anchor) {
                    broken.push(format!("{at}: no heading `#{anchor}` in {}", file.display()));
                }
            }
        }
    }
    assert!(checked > 50, "only {checked} links found: the extraction is broken");
    assert!(broken.is_empty(), "{} broken links:\n{}", broken.len(), broken.join("\n"));
}

#[test]
fn the_book_builds() {
    let mdbook = cache_dir().join("tools/bin/mdbook");
    assert!(mdbook.exists(), "{} is missing: run `bash scripts/setup.sh`", mdbook.display());
    let out_dir = tempfile::tempdir().unwrap();
    let out = Command::new(&mdbook).arg("build").arg(repo_root()).arg("-d").arg(out_dir.path()).output().unwrap();
    let log = output_text(&out);
    assert!(out.status.success(), "mdbook build failed:\n{log}");
    assert!(!log.contains("WARN") && !log.contains("ERROR"), "mdbook build warned:\n{log}");
    for page in ["index.html", "operator.html", "bringup.html", "install.html", "reference.html"] {
        assert!(out_dir.path().join(page).exists(), "the book has no {page}: {log}");
    }
}

/// The blocks a guide marks `<!-- docs-check: runs -->` (the line before the fence) of
/// getting started and the curator guide, in order: the pages' text.
fn runnable_blocks(page: &str) -> Vec<(usize, String)> {
    let text = std::fs::read_to_string(repo_root().join("docs").join(page)).unwrap();
    let lines: Vec<&str> = text.lines().collect();
    let mut out = Vec::new();
    let mut i = 0;
    while i < lines.len() {
        if lines[i].trim() == "<!-- docs-check: runs -->" {
            assert!(
                lines.get(i + 1).is_some_and(|l| l.starts_with("```sh")),
                "{page}:{}: the marker is not above a sh block",
                i + 1
            );
            let body: Vec<&str> = lines[i + 2..].iter().take_while(|l| !l.starts_with("```")).copied().collect();
            out.push((i + 3, body.join("\n")));
            i += 2 + body.len();
        }
        i += 1;
    }
    out
}

/// Following the guides literally works: after `labrig demo` (three episodes in
/// `out/demo/episodes`), every block the getting-started and curator guides mark as running as
/// written runs, in the pages' order, in the folder the demo ran in, with the built programs on
/// PATH (the guide's `export PATH=...`), and exits 0.
#[test]
fn the_guides_marked_blocks_run_as_written_on_the_demos_episodes() {
    let dir = tempfile::tempdir().unwrap();
    let domain = labrig_tests::domain_for("docs_guides_run").to_string();
    let ns = format!("docs_guides_{}", std::process::id());
    let bin_dir = labrig_bin().parent().unwrap().to_owned();
    // Every program a block runs, built (the sim for replay and snapshot, the dataset tools).
    for (package, program) in
        [("labrig-sim", "labrig-sim"), ("labrig-dataset", "labrig-dataset"), ("labrig-droid", "labrig-droid")]
    {
        workspace_bin(package, program);
    }
    let path = format!("{}:{}", bin_dir.display(), std::env::var("PATH").unwrap_or_default());
    let run = |what: &str, script: &str| {
        let out = Command::new("bash")
            .args(["-euo", "pipefail", "-c", script])
            .current_dir(dir.path())
            .env("PATH", &path)
            .env("ROS_DOMAIN_ID", &domain)
            .env(labrig_runtime::frames::NAMESPACE_ENV, &ns)
            .output()
            .unwrap();
        assert!(out.status.success(), "{what} failed:\n{script}\n{}", output_text(&out));
        output_text(&out)
    };
    let demo = run("labrig demo", &format!("labrig demo --domain-id {domain}"));
    assert!(demo.contains("3 of 3 episodes recorded"), "{demo}");
    // Every step of every episode, the first one's first steps too, has every camera's frame.
    let inspected = run("inspect", "for e in out/demo/episodes/*/*/*; do labrig inspect --json \"$e\"; done");
    let reports: Vec<serde_json::Value> =
        inspected.lines().filter_map(|l| serde_json::from_str(l.trim_start_matches("stdout: ")).ok()).collect();
    assert_eq!(reports.len(), 3, "{inspected}");
    for r in &reports {
        assert_eq!(r["cameras"].as_array().map(Vec::len), Some(5), "{r:#}");
        for c in r["cameras"].as_array().unwrap() {
            assert_eq!(c["steps_without_frame"], 0, "{}: {c}", r["path"]);
        }
    }
    let mut ran = 0;
    for (page, least) in [("getting-started.md", 2), ("curator.md", 4)] {
        let blocks = runnable_blocks(page);
        assert!(blocks.len() >= least, "{page}: {} runnable blocks, expected at least {least}", blocks.len());
        for (line, script) in blocks {
            run(&format!("docs/{page}:{line}"), &script);
            ran += 1;
        }
    }
    // What the curator's blocks made: the folder of target demos retrieved its own three.
    let manifest: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.path().join("out/manifest.json")).unwrap()).unwrap();
    assert_eq!(manifest["episodes"].as_array().map(Vec::len), Some(3), "{manifest:#}");
    assert!(ran >= 6);
}
