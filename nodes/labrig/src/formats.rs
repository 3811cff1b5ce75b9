//! The dataset formats `labrig export` and `labrig import` convert, one row each: the format's
//! name on the command line, the program beside `labrig` that converts it, and that program's
//! subcommands. A new format: its reader and writer in its crate (DROID's in `droid/`, the others
//! in `dataset/`), its `export-*` / `import-*` subcommands in that crate's program, and a row here.

/// One format and the program that converts it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Format {
    /// `labrig export <name> ...`
    pub name: &'static str,
    /// The program beside `labrig` that converts it.
    pub program: &'static str,
    /// Its subcommands for `labrig export` and `labrig import`.
    pub export: &'static str,
    pub import: &'static str,
    /// What the format is, for `labrig export --help`.
    pub about: &'static str,
}

impl Format {
    /// The program's subcommand for `verb` (`export` or `import`).
    pub fn subcommand(&self, verb: &str) -> &'static str {
        if verb == "import" { self.import } else { self.export }
    }
}

pub const FORMATS: &[Format] = &[
    Format { name: "droid", program: "labrig-droid", export: "export", import: "import", about: "DROID's raw layout" },
    Format {
        name: "droid-mcap",
        program: "labrig-droid",
        export: "export-mcap",
        import: "import-mcap",
        about: "DROID's MCAP layout",
    },
    Format {
        name: "lerobot",
        program: "labrig-dataset",
        export: "export-lerobot",
        import: "import-lerobot",
        about: "LeRobot's dataset format v3.0 or v2.1",
    },
];

/// The format named `name`.
pub fn find(name: &str) -> Option<&'static Format> {
    FORMATS.iter().find(|f| f.name == name)
}

/// `droid, droid-mcap, lerobot` (with `sep` between).
pub fn names(sep: &str) -> String {
    FORMATS.iter().map(|f| f.name).collect::<Vec<_>>().join(sep)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_are_unique_and_each_verb_has_a_subcommand() {
        let mut seen = std::collections::BTreeSet::new();
        for f in FORMATS {
            assert!(seen.insert(f.name), "{} listed twice", f.name);
            assert!(f.subcommand("export").starts_with("export"), "{f:?}");
            assert!(f.subcommand("import").starts_with("import"), "{f:?}");
        }
        assert_eq!(names(", "), "droid, droid-mcap, lerobot");
        assert_eq!(find("lerobot").map(|f| f.program), Some("labrig-dataset"));
        assert!(find("rlds").is_none());
    }
}
