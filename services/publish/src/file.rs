//! The trajectory file of a publisher that may be killed and restarted, or find its disk
//! full: a restarted publisher appends (what was written stays), a line cut short by the
//! death of its writer is removed, and a record that cannot be written is left out whole
//! while the stream to subscribers goes on.

use std::fs::{File, OpenOptions};
use std::io::{Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};

use crate::{JsonLinesSink, TrajectoryRecord};

/// The JSON Lines file of one run.
pub struct TrajectoryFile {
    path: PathBuf,
    sink: JsonLinesSink<File>,
    /// Bytes of whole lines in the file.
    whole_len: u64,
    /// Records left out since writing last failed: (first frame, count).
    failing: Option<(u64, u64)>,
    /// Records left out in all.
    left_out: u64,
}

impl TrajectoryFile {
    /// Creates the file (emptied), or with `append` opens it to go on after the lines it
    /// holds (a restart), cutting a last line left unfinished.
    pub fn open(path: &Path, append: bool) -> Result<Self, String> {
        let name = || path.display();
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).map_err(|e| format!("creating `{}`: {e}", dir.display()))?;
        }
        let mut file = OpenOptions::new()
            .create(true)
            .write(true)
            .read(true)
            .truncate(!append)
            .open(path)
            .map_err(|e| format!("opening `{}`: {e}", name()))?;
        let whole_len =
            if append { whole_lines_len(&mut file).map_err(|e| format!("reading `{}`: {e}", name()))? } else { 0 };
        let len = file.metadata().map_err(|e| format!("`{}`: {e}", name()))?.len();
        if whole_len < len {
            tracing::warn!(
                "`{}`: removing the unfinished last line ({} bytes) of the previous publisher",
                name(),
                len - whole_len
            );
            file.set_len(whole_len).map_err(|e| format!("cutting `{}`: {e}", name()))?;
        }
        file.seek(SeekFrom::Start(whole_len)).map_err(|e| format!("`{}`: {e}", name()))?;
        Ok(Self { path: path.to_path_buf(), sink: JsonLinesSink::new(file), whole_len, failing: None, left_out: 0 })
    }

    /// Appends `record`. A failure (a full disk) is logged, once per run of failures, and
    /// whatever part of the line reached the file is cut: the file keeps only whole lines.
    pub fn write(&mut self, record: &TrajectoryRecord) {
        let written = JsonLinesSink::<File>::line(record).and_then(|line| {
            reserve(self.sink.get_ref(), self.whole_len, line.len())?;
            self.sink.write_line(&line)
        });
        match written {
            Ok(()) => {
                if let Some((first, count)) = self.failing.take() {
                    tracing::warn!(
                        "writing `{}` again: the {count} record(s) from frame {first} on are not in it ({} in all)",
                        self.path.display(),
                        self.left_out
                    );
                }
                self.whole_len = self.sink.get_ref().stream_position().unwrap_or(self.whole_len);
            }
            Err(error) => {
                self.left_out += 1;
                match self.failing.as_mut() {
                    Some((_, count)) => *count += 1,
                    None => {
                        tracing::error!(
                            "cannot write frame {} to `{}`: {error}; the stream goes on, records left out of the file until \
                             it can be written again",
                            record.frame,
                            self.path.display()
                        );
                        self.failing = Some((record.frame, 1));
                    }
                }
                let file = self.sink.get_ref();
                // Only a fragment is cut: a file left as it was stays untouched.
                let grown = file.metadata().map_or(true, |m| m.len() > self.whole_len);
                let cut = if grown { file.set_len(self.whole_len) } else { Ok(()) }
                    .and_then(|()| (&*file).seek(SeekFrom::Start(self.whole_len)));
                if let Err(e) = cut {
                    tracing::error!("cannot cut a partial line from `{}`: {e}", self.path.display());
                }
            }
        }
    }

    /// Records left out of the file so far.
    pub fn left_out(&self) -> u64 {
        self.left_out
    }
}

/// Length of `file`'s content up to and including its last newline.
fn whole_lines_len(file: &mut File) -> std::io::Result<u64> {
    let len = file.metadata()?.len();
    // Lines are a few hundred bytes: the last newline is near the end.
    let mut end = len;
    let mut block = vec![0u8; 64 * 1024];
    while end > 0 {
        let start = end.saturating_sub(block.len() as u64);
        let chunk = &mut block[..(end - start) as usize];
        file.seek(SeekFrom::Start(start))?;
        file.read_exact(chunk)?;
        if let Some(i) = chunk.iter().rposition(|&b| b == b'\n') {
            return Ok(start + i as u64 + 1);
        }
        end = start;
    }
    Ok(0)
}

/// Reserves `len` bytes of disk past `offset` without changing the file's length, so that
/// the write that follows either fits whole or fails before a byte of it is written: a full
/// disk used to take the first part of a line, which a reader following the file saw before
/// it was cut (found by the fault campaign's disk-full). Where nothing can be reserved (a
/// device, a pipe, `EOPNOTSUPP`) the write goes ahead, and a fragment is cut as before.
fn reserve(file: &File, offset: u64, len: usize) -> std::io::Result<()> {
    use rustix::fs::{fallocate, FallocateFlags};
    use rustix::io::Errno;
    match fallocate(file, FallocateFlags::KEEP_SIZE, offset, len as u64) {
        Err(e @ (Errno::NOSPC | Errno::DQUOT | Errno::FBIG)) => Err(e.into()),
        // Devices, pipes and file systems without reservations: the write goes ahead.
        _ => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::BTreeMap;

    fn record(frame: u64) -> TrajectoryRecord {
        TrajectoryRecord {
            frame,
            t: frame as f64 / 30.0,
            objects: BTreeMap::new(),
            dropped_frames: 0,
            missing_views: 0,
        }
    }

    fn frames_in(path: &Path) -> Vec<u64> {
        std::fs::read_to_string(path)
            .unwrap()
            .lines()
            .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap()["frame"].as_u64().unwrap())
            .collect()
    }

    #[test]
    fn a_restarted_publisher_appends_and_cuts_the_line_its_predecessor_left_unfinished() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("out/t.jsonl");
        let mut first = TrajectoryFile::open(&path, false).unwrap();
        first.write(&record(1));
        first.write(&record(2));
        drop(first);
        // Killed in the middle of a line.
        let mut text = std::fs::read(&path).unwrap();
        text.extend_from_slice(b"{\"frame\":3,\"t\":0.1");
        std::fs::write(&path, text).unwrap();
        let mut second = TrajectoryFile::open(&path, true).unwrap();
        second.write(&record(4));
        assert_eq!(frames_in(&path), vec![1, 2, 4]);
        // A new run starts the file afresh.
        let mut third = TrajectoryFile::open(&path, false).unwrap();
        third.write(&record(9));
        assert_eq!(frames_in(&path), vec![9]);
    }

    #[test]
    fn a_file_of_only_an_unfinished_line_is_emptied_on_append() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("t.jsonl");
        std::fs::write(&path, b"{\"fra").unwrap();
        let mut file = TrajectoryFile::open(&path, true).unwrap();
        file.write(&record(5));
        assert_eq!(frames_in(&path), vec![5]);
    }

    #[test]
    fn a_full_disk_leaves_records_out_and_the_writer_goes_on() {
        // Linux's /dev/full fails every write with ENOSPC.
        if !Path::new("/dev/full").exists() {
            eprintln!("skipping: no /dev/full");
            return;
        }
        let mut file = TrajectoryFile::open(Path::new("/dev/full"), true).unwrap();
        for frame in 0..5 {
            file.write(&record(frame));
        }
        assert_eq!(file.left_out(), 5);
    }

    #[test]
    fn a_full_disk_takes_not_a_byte_of_a_line_it_cannot_hold() {
        // A 64 KiB tmpfs: root only (as CI runs); elsewhere the test says why it skips.
        let dir = tempfile::tempdir().unwrap();
        let mount = dir.path().join("small");
        std::fs::create_dir(&mount).unwrap();
        let mounted = std::process::Command::new("mount")
            .args(["-t", "tmpfs", "-o", "size=64k", "tmpfs"])
            .arg(&mount)
            .stderr(std::process::Stdio::null())
            .status()
            .is_ok_and(|s| s.success());
        if !mounted {
            eprintln!("skipping: cannot mount a small tmpfs (not root?)");
            return;
        }
        let path = mount.join("t.jsonl");
        let outcome = std::panic::catch_unwind(|| {
            let mut file = TrajectoryFile::open(&path, false).unwrap();
            file.write(&record(0));
            // Every free page taken: the trajectory file's own last page still has room.
            let mut filler = File::create(mount.join("filler")).unwrap();
            while std::io::Write::write_all(&mut filler, &[0u8; 4096]).is_ok() {}
            let mut frame = 1;
            loop {
                let before = std::fs::metadata(&path).unwrap();
                file.write(&record(frame));
                if file.left_out() > 0 {
                    // The line that needed a new page: the file was not touched at all.
                    let after = std::fs::metadata(&path).unwrap();
                    assert_eq!(after.len(), before.len());
                    assert_eq!(after.modified().unwrap(), before.modified().unwrap(), "a part of the line was written");
                    break;
                }
                frame += 1;
                assert!(frame < 1000, "the disk fills");
            }
            assert_eq!(frames_in(&path), (0..frame).collect::<Vec<_>>());
            // Room again: the writer goes on.
            drop(filler);
            std::fs::remove_file(mount.join("filler")).unwrap();
            file.write(&record(frame + 1));
            assert_eq!(frames_in(&path).last(), Some(&(frame + 1)));
        });
        let _ = std::process::Command::new("umount").arg("-l").arg(&mount).status();
        if let Err(panic) = outcome {
            std::panic::resume_unwind(panic);
        }
    }
}
