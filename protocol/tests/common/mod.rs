//! What the calibration tests share: the bad-file fixtures and how each must fail.

use std::path::Path;

use handflow_protocol::{Rig, RigError};

/// The bad calibration files, one per error (`tests/fixtures/bad/` of the repository).
pub const BAD_DIR: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../tests/fixtures/bad/");

/// Every fixture of `table` fails to load with an error naming the file and holding each of
/// its expected fragments; the fixtures whose names start with one of `prefixes` are exactly
/// the table's.
pub fn assert_bad_fixtures(table: &[(&str, &[&str])], prefixes: &[&str]) {
    for (file, expected) in table {
        let path = Path::new(BAD_DIR).join(file);
        assert!(path.is_file(), "missing fixture {}", path.display());
        let error = Rig::load(&path).expect_err(file);
        assert!(matches!(error, RigError::InFile { .. }), "{file}: {error:?}");
        let message = error.to_string();
        assert!(message.contains(file), "{file}: message lacks the path: {message}");
        for needle in *expected {
            assert!(message.contains(needle), "{file}: message lacks {needle:?}: {message}");
        }
    }
    let mut files: Vec<String> = std::fs::read_dir(BAD_DIR)
        .expect("fixture directory")
        .map(|entry| entry.expect("directory entry").file_name().to_string_lossy().into_owned())
        .filter(|name| prefixes.iter().any(|prefix| name.starts_with(prefix)))
        .collect();
    files.sort();
    let mut listed: Vec<String> = table.iter().map(|(file, _)| (*file).to_owned()).collect();
    listed.sort();
    assert_eq!(files, listed, "every fixture is in the table, and only those");
}
