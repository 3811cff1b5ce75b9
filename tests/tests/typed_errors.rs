//! Library errors are types a caller can match on (STYLE.md: `thiserror` enums with structured
//! fields), never `String`: every workspace crate's `src/` is read for a `Result<_, String>`,
//! nested generics and multi-line types included, in signatures, closures and type aliases.
//! Not read: `tests/` folders, `main.rs`, `src/bin/` (a program's errors are `anyhow`'s), and a
//! file's lines from `#[cfg(test)]` on. Comments and string literals are not code.

use std::path::{Path, PathBuf};

/// The workspace's member folders, from the root Cargo.toml.
fn members(root: &Path) -> Vec<String> {
    let text = std::fs::read_to_string(root.join("Cargo.toml")).unwrap();
    let manifest: toml::Value = toml::from_str(&text).unwrap();
    let members: Vec<String> = manifest["workspace"]["members"]
        .as_array()
        .expect("[workspace] members")
        .iter()
        .map(|m| m.as_str().expect("a member is a path").to_owned())
        .collect();
    for m in &members {
        assert!(root.join(m).join("Cargo.toml").is_file(), "workspace member {m} has no Cargo.toml");
    }
    members
}

/// The library sources under `dir` (a crate's `src/` at `top`).
fn library_files(dir: &Path, top: bool, out: &mut Vec<PathBuf>) {
    let mut entries: Vec<PathBuf> = std::fs::read_dir(dir).unwrap().map(|e| e.unwrap().path()).collect();
    entries.sort();
    for p in entries {
        let name = p.file_name().unwrap().to_string_lossy().into_owned();
        if p.is_dir() {
            if name != "tests" && !(top && name == "bin") {
                library_files(&p, false, out);
            }
        } else if name.ends_with(".rs") && name != "main.rs" {
            out.push(p);
        }
    }
}

/// One character of a literal or comment as blank (newlines kept, so lines still count).
fn blank(out: &mut String, ch: char) {
    out.push(if ch == '\n' { '\n' } else { ' ' });
}

/// A string or char literal opening at `c[i]` with `quote`, blanked through its closing quote
/// (escapes skipped); returns where the code goes on.
fn blank_quoted(c: &[char], mut i: usize, quote: char, out: &mut String) -> usize {
    blank(out, quote);
    i += 1;
    while i < c.len() && c[i] != quote {
        if c[i] == '\\' {
            blank(out, c[i]);
            i += 1;
        }
        if i < c.len() {
            blank(out, c[i]);
            i += 1;
        }
    }
    if i < c.len() {
        blank(out, quote);
        i += 1;
    }
    i
}

/// `src` with comments, string and char literals blanked (newlines kept, so lines still count),
/// and nothing from a line `#[cfg(test)]` on.
fn code_of(src: &str) -> String {
    let end = src
        .lines()
        .scan(0, |at, l| {
            let start = *at;
            *at += l.len() + 1;
            Some((start, l))
        })
        .find(|(_, l)| l.trim() == "#[cfg(test)]")
        .map_or(src.len(), |(start, _)| start);
    let c: Vec<char> = src[..end].chars().collect();
    let word = |ch: char| ch.is_alphanumeric() || ch == '_';
    let mut out = String::with_capacity(c.len());
    let mut i = 0;
    while i < c.len() {
        match c[i] {
            '/' if c.get(i + 1) == Some(&'/') => {
                while i < c.len() && c[i] != '\n' {
                    blank(&mut out, c[i]);
                    i += 1;
                }
            }
            '/' if c.get(i + 1) == Some(&'*') => {
                let mut depth = 0;
                while i < c.len() {
                    if c[i] == '/' && c.get(i + 1) == Some(&'*') {
                        depth += 1;
                        out.push_str("  ");
                        i += 2;
                    } else if c[i] == '*' && c.get(i + 1) == Some(&'/') {
                        depth -= 1;
                        out.push_str("  ");
                        i += 2;
                        if depth == 0 {
                            break;
                        }
                    } else {
                        blank(&mut out, c[i]);
                        i += 1;
                    }
                }
            }
            // A raw string: r"..", r#".."#, br"..".
            'r' if i == 0 || !word(c[i - 1]) || (c[i - 1] == 'b' && (i == 1 || !word(c[i - 2]))) => {
                let mut j = i + 1;
                while c.get(j) == Some(&'#') {
                    j += 1;
                }
                if c.get(j) != Some(&'"') {
                    out.push('r');
                    i += 1;
                    continue;
                }
                let hashes = j - i - 1;
                let mut k = j + 1;
                while k < c.len() && !(c[k] == '"' && (0..hashes).all(|h| c.get(k + 1 + h) == Some(&'#'))) {
                    k += 1;
                }
                let stop = (k + 1 + hashes).min(c.len());
                for &ch in &c[i..stop] {
                    blank(&mut out, ch);
                }
                i = stop;
            }
            '"' => i = blank_quoted(&c, i, '"', &mut out),
            // A char literal ('x', '\n', '\u{..}'), not a lifetime ('a).
            '\'' if c.get(i + 1) == Some(&'\\') || c.get(i + 2) == Some(&'\'') => {
                i = blank_quoted(&c, i, '\'', &mut out)
            }
            ch => {
                out.push(ch);
                i += 1;
            }
        }
    }
    out
}

/// The 1-based lines of code where a `Result<T, String>` type starts.
fn string_results(code: &str) -> Vec<usize> {
    let c: Vec<char> = code.chars().collect();
    let word = |ch: char| ch.is_alphanumeric() || ch == '_';
    let mut lines = Vec::new();
    let mut i = 0;
    while let Some(at) = code_char_find(&c, i, "Result") {
        i = at + 1;
        if (at > 0 && word(c[at - 1])) || c.get(at + 6).copied().is_some_and(word) {
            continue;
        }
        let mut j = at + 6;
        while c.get(j).is_some_and(|ch| ch.is_whitespace()) {
            j += 1;
        }
        if c.get(j) != Some(&'<') {
            continue;
        }
        // The generic arguments up to the matching '>', split at depth-1 commas.
        let (mut depth, mut k, mut args, mut arg) = (0usize, j, Vec::new(), String::new());
        while k < c.len() {
            let ch = c[k];
            let arrow = ch == '>' && k > 0 && (c[k - 1] == '-' || c[k - 1] == '=');
            match ch {
                '<' | '(' | '[' | '{' => depth += 1,
                '>' | ')' | ']' | '}' if !arrow => depth -= 1,
                _ => {}
            }
            if depth == 0 {
                args.push(std::mem::take(&mut arg));
                break;
            }
            if depth == 1 && ch == ',' {
                args.push(std::mem::take(&mut arg));
            } else if !(depth == 1 && ch == '<' && k == j) {
                arg.push(ch);
            }
            k += 1;
        }
        // (A trailing comma leaves an empty last argument.)
        if args.last().is_some_and(|a| a.trim().is_empty()) {
            args.pop();
        }
        let error: String = args.last().map(|a| a.split_whitespace().collect()).unwrap_or_default();
        if args.len() >= 2 && ["String", "std::string::String", "alloc::string::String"].contains(&error.as_str()) {
            lines.push(c[..at].iter().filter(|&&ch| ch == '\n').count() + 1);
        }
    }
    lines
}

fn code_char_find(c: &[char], from: usize, needle: &str) -> Option<usize> {
    let n: Vec<char> = needle.chars().collect();
    (from..c.len().saturating_sub(n.len() - 1)).find(|&i| c[i..i + n.len()] == n[..])
}

/// Every `Result<_, String>` in the libraries: `file:line: the line`.
fn offenders(root: &Path) -> Vec<String> {
    let mut found = Vec::new();
    for member in members(root) {
        let src = root.join(&member).join("src");
        if !src.is_dir() {
            continue;
        }
        let mut files = Vec::new();
        library_files(&src, true, &mut files);
        for f in files {
            let rel = f.strip_prefix(root).unwrap().to_string_lossy().replace('\\', "/");
            let text = std::fs::read_to_string(&f).unwrap();
            for line in string_results(&code_of(&text)) {
                found.push(format!("{rel}:{line}: {}", text.lines().nth(line - 1).unwrap_or("").trim()));
            }
        }
    }
    found
}

#[test]
fn libraries_return_no_string_errors() {
    let found = offenders(&labrig_tests::repo_root());
    assert!(
        found.is_empty(),
        "library functions return `Result<_, String>`; give the error a thiserror type a caller can match on \
         (STYLE.md), `.to_string()` only where it crosses a wire or a report:\n{}",
        found.join("\n")
    );
}

#[test]
fn the_check_sees_string_errors_however_written() {
    // Guards the guard: each of these is one (on the line given).
    let code = code_of(
        "fn a() -> Result<(), String> {}\n\
         fn b() -> Result<Vec<(u8, u32)>, String> {}\n\
         fn c(\n    x: u8,\n) -> Result<\n    BTreeMap<String, Vec<u8>>,\n    String,\n> {}\n\
         let f = |k: usize| -> Result<Value, String> { todo() };\n\
         type R<T> = std::result::Result<T, std::string::String>;\n\
         fn d(f: &dyn Fn(u8) -> Result<u8, String>) -> Result<Box<dyn Fn(u8) -> u8>, String> {}\n",
    );
    assert_eq!(string_results(&code), vec![1, 2, 5, 9, 10, 11, 11]);
    // ... and none of these.
    let code = code_of(
        "fn a() -> Result<String, Error> {}\n\
         fn b() -> Result<(u64, String), E> {}\n\
         fn c() -> io::Result<String> {}\n\
         type Reply = Result<ActionChunk, (u64, String)>;\n\
         // fn d() -> Result<(), String>\n\
         /* Result<(), String> */ let s = \"Result<(), String>\";\n\
         let r = r#\"Result<(), String>\"#; let q = '\"'; fn e<'a>(x: &'a str) -> MyResult<u8, String> {}\n\
         fn f() -> Result<Vec<Option<u8>>, Strings> {}\n\
         #[cfg(test)]\n\
         fn g() -> Result<(), String> {}\n",
    );
    assert_eq!(string_results(&code), Vec::<usize>::new());
}
