//! When each frame set was captured: `frames.csv`, or a caliscope `timestamps.csv`.

use std::collections::BTreeMap;
use std::path::Path;

use super::RecordingError;

/// The frame table of handflow's own layout.
pub const FRAMES_FILE: &str = "frames.csv";
/// caliscope's capture times.
pub const CALISCOPE_TIMESTAMPS_FILE: &str = "timestamps.csv";
/// The name older caliscope versions give the same table (cameras as `port`).
pub const CALISCOPE_FRAME_HISTORY_FILE: &str = "frame_time_history.csv";

/// One frame set of a caliscope session: which frame of each camera belongs to it.
#[derive(Clone, Debug, PartialEq)]
pub struct SyncedSet {
    /// caliscope's `sync_index`.
    pub sync_index: u64,
    /// Per camera id: the frame's position in that camera's video and its capture time,
    /// seconds.
    pub frames: BTreeMap<u64, (usize, f64)>,
}

/// Parses `frames.csv`: a `frame,timestamp` header, then rows with a frame number and a
/// finite timestamp in seconds, both strictly increasing.
pub fn read_frame_table(path: &Path) -> Result<Vec<(u64, f64)>, RecordingError> {
    let err = |line: usize, problem: String| RecordingError::Frames { path: path.to_path_buf(), line, problem };
    let text = handflow_protocol::read_text_capped(path).map_err(|e| err(0, format!("cannot be read: {e}")))?;
    let mut lines = text.lines().enumerate().filter(|(_, l)| !l.trim().is_empty());
    match lines.next() {
        Some((_, header)) => {
            let cols: Vec<String> = header.split(',').map(|c| c.trim().to_ascii_lowercase()).collect();
            if cols != ["frame", "timestamp"] {
                return Err(err(1, format!("expected the header `frame,timestamp`, found `{}`", header.trim())));
            }
        }
        None => return Err(err(0, "is empty (expected a `frame,timestamp` header and one row per frame)".into())),
    }
    let mut rows: Vec<(u64, f64)> = Vec::new();
    for (i, line) in lines {
        let n = i + 1;
        let fields: Vec<&str> = line.split(',').map(str::trim).collect();
        let [frame, timestamp] = fields[..] else {
            return Err(err(n, format!("expected 2 fields (frame,timestamp), found {}", fields.len())));
        };
        let frame: u64 = frame.parse().map_err(|_| err(n, format!("frame `{frame}` is not a non-negative integer")))?;
        let timestamp: f64 =
            timestamp.parse().map_err(|_| err(n, format!("timestamp `{timestamp}` is not a number")))?;
        if !timestamp.is_finite() {
            return Err(err(n, format!("frame {frame}: timestamp {timestamp} is not finite")));
        }
        if let Some(&(prev_frame, prev_time)) = rows.last() {
            if frame <= prev_frame {
                return Err(err(
                    n,
                    format!("frame {frame} does not follow frame {prev_frame} (frame numbers must increase)"),
                ));
            }
            if timestamp <= prev_time {
                return Err(err(
                    n,
                    format!(
                        "frame {frame}: timestamp {timestamp} is not after frame {prev_frame}'s {prev_time} \
                         (timestamps must increase)"
                    ),
                ));
            }
        }
        rows.push((frame, timestamp));
    }
    if rows.is_empty() {
        return Err(err(0, "lists no frame".into()));
    }
    Ok(rows)
}

/// One camera's row of a caliscope file: `sync_index`, `frame_index` when given, capture
/// time and line number.
type Row = (u64, Option<u64>, f64, usize);

/// Parses a caliscope `timestamps.csv` or `frame_time_history.csv` (`[sync_index,]
/// cam_id|port[, frame_index], frame_time`, in any column order) into frame sets, in
/// `sync_index` order.
///
/// caliscope's `frame_index` counts a camera's captured frames; its video holds them from
/// the first listed one on, so a frame's position in the video is its `frame_index` minus
/// the camera's first. Without `frame_index`, a camera's rows in time order are its video's
/// frames in order. Without `sync_index`, frames are grouped by capture time as caliscope's
/// synchroniser does (see `group_by_time`).
pub fn read_caliscope_timestamps(path: &Path) -> Result<Vec<SyncedSet>, RecordingError> {
    let err = |line: usize, problem: String| RecordingError::Frames { path: path.to_path_buf(), line, problem };
    let text = handflow_protocol::read_text_capped(path).map_err(|e| err(0, format!("cannot be read: {e}")))?;
    let mut lines = text.lines().enumerate().filter(|(_, l)| !l.trim().is_empty());
    let Some((_, header)) = lines.next() else {
        return Err(err(0, "is empty (expected a `sync_index,cam_id,frame_index,frame_time` header)".into()));
    };
    let columns: Vec<String> = header.split(',').map(|c| c.trim().to_ascii_lowercase()).collect();
    let column = |name: &str| columns.iter().position(|c| c == name);
    let sync_col = column("sync_index");
    let (Some(cam_col), Some(time_col)) = (column("cam_id").or_else(|| column("port")), column("frame_time")) else {
        return Err(err(
            1,
            format!(
                "expected the columns `cam_id` (or `port`) and `frame_time` (and optionally `sync_index`, \
                 `frame_index`), found `{}`",
                header.trim()
            ),
        ));
    };
    let index_col = column("frame_index");
    // Without sync_index: every row first, grouped by time below.
    let mut unsynced: Vec<(u64, Option<u64>, f64, usize)> = Vec::new();
    // (sync_index, cam_id) -> (frame_index or None, time, line)
    let mut rows: BTreeMap<(u64, u64), (Option<u64>, f64, usize)> = BTreeMap::new();
    for (i, line) in lines {
        let n = i + 1;
        let fields: Vec<&str> = line.split(',').map(str::trim).collect();
        if fields.len() != columns.len() {
            return Err(err(n, format!("expected {} fields, found {}", columns.len(), fields.len())));
        }
        let integer = |col: usize, name: &str| -> Result<u64, RecordingError> {
            fields[col].parse().map_err(|_| err(n, format!("{name} `{}` is not a non-negative integer", fields[col])))
        };
        let cam = integer(cam_col, "cam_id")?;
        let index = index_col.map(|c| integer(c, "frame_index")).transpose()?;
        let time: f64 = fields[time_col]
            .parse()
            .ok()
            .filter(|t: &f64| t.is_finite())
            .ok_or_else(|| err(n, format!("frame_time `{}` is not a finite number", fields[time_col])))?;
        let Some(sync_col) = sync_col else {
            unsynced.push((cam, index, time, n));
            continue;
        };
        let sync = integer(sync_col, "sync_index")?;
        if let Some(&(_, _, first)) = rows.get(&(sync, cam)) {
            return Err(err(n, format!("camera {cam} appears twice in sync_index {sync} (first on line {first})")));
        }
        rows.insert((sync, cam), (index, time, n));
    }
    if sync_col.is_none() {
        rows = group_by_time(&unsynced);
    }
    if rows.is_empty() {
        return Err(err(0, "lists no frame".into()));
    }
    // Each camera's rows in sync order give its video positions.
    let mut per_camera: BTreeMap<u64, Vec<Row>> = BTreeMap::new();
    for (&(sync, cam), &(index, time, line)) in &rows {
        per_camera.entry(cam).or_default().push((sync, index, time, line));
    }
    let mut sets: BTreeMap<u64, SyncedSet> = BTreeMap::new();
    for (cam, list) in &per_camera {
        let first_index = list.iter().filter_map(|r| r.1).min();
        let mut previous: Option<(u64, u64)> = None;
        for (rank, &(sync, index, time, line)) in list.iter().enumerate() {
            let position = match (index, first_index) {
                (Some(index), Some(first)) => {
                    if let Some((prev, prev_sync)) = previous {
                        if index <= prev {
                            return Err(err(
                                line,
                                format!(
                                    "camera {cam}: frame_index {index} at sync_index {sync} does not follow \
                                     {prev} at sync_index {prev_sync}"
                                ),
                            ));
                        }
                    }
                    previous = Some((index, sync));
                    (index - first) as usize
                }
                _ => rank,
            };
            sets.entry(sync)
                .or_insert_with(|| SyncedSet { sync_index: sync, frames: BTreeMap::new() })
                .frames
                .insert(*cam, (position, time));
        }
    }
    Ok(sets.into_values().collect())
}

/// Sync indices for rows without them: repeatedly, the earliest next frame of any camera
/// opens a set, and each camera's next frame joins it when captured within half a frame
/// interval (the median over cameras) of it; a camera whose next frame is later is absent
/// from that set. The greedy rule caliscope's own synchroniser follows.
fn group_by_time(rows: &[(u64, Option<u64>, f64, usize)]) -> BTreeMap<(u64, u64), (Option<u64>, f64, usize)> {
    let mut per_camera: BTreeMap<u64, Vec<(Option<u64>, f64, usize)>> = BTreeMap::new();
    for &(cam, index, time, line) in rows {
        per_camera.entry(cam).or_default().push((index, time, line));
    }
    let mut intervals: Vec<f64> = Vec::new();
    for list in per_camera.values_mut() {
        list.sort_by(|a, b| a.1.total_cmp(&b.1));
        intervals.extend(list.windows(2).map(|w| w[1].1 - w[0].1).filter(|d| *d > 0.0));
    }
    intervals.sort_by(f64::total_cmp);
    let half = intervals.get(intervals.len() / 2).map_or(f64::INFINITY, |d| d / 2.0);
    let mut next: BTreeMap<u64, usize> = per_camera.keys().map(|&c| (c, 0)).collect();
    let mut grouped = BTreeMap::new();
    for sync in 0u64.. {
        let heads: Vec<(u64, f64)> =
            per_camera.iter().filter_map(|(c, list)| list.get(next[c]).map(|r| (*c, r.1))).collect();
        let Some(first) = heads.iter().map(|h| h.1).min_by(f64::total_cmp) else { break };
        for (cam, time) in heads {
            // A difference, not `first + half`: where `half` is below `first`'s precision the
            // sum is `first` itself, no camera would join, and the loop would never end.
            if time - first < half {
                let k = next[&cam];
                grouped.insert((sync, cam), per_camera[&cam][k]);
                next.insert(cam, k + 1);
            }
        }
    }
    grouped
}

#[cfg(test)]
mod tests {
    use super::*;

    fn write(text: &str) -> (tempfile::TempDir, std::path::PathBuf) {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join(CALISCOPE_TIMESTAMPS_FILE);
        std::fs::write(&path, text).expect("write");
        (dir, path)
    }

    #[test]
    fn grouping_by_time_ends_when_the_frame_interval_is_below_the_times_precision() {
        // Found by fuzzing: a camera at 1e20 s (spacing 16384 s there) and one whose frames
        // are a microsecond apart made half an interval vanish in `1e20 + half`.
        let (_d, path) = write(
            "cam_id,frame_time
0,1e20
0,1.00000000000000016384e20
1,0.0
1,0.000001
1,0.000002
",
        );
        let sets = read_caliscope_timestamps(&path).expect("parses");
        assert_eq!(sets.len(), 5, "every frame in a set of its own: {sets:?}");
    }

    #[test]
    fn caliscope_rows_group_by_sync_index_with_frame_index() {
        // caliscope's order (cameras shuffled within a set); frame_index starts at 26 as in
        // a real session whose videos begin there.
        let (_d, path) = write(
            "sync_index,cam_id,frame_index,frame_time\n26,1,26,10.001\n26,0,26,10.0\n27,0,27,10.17\n27,1,27,10.2\n\
             28,0,29,10.5\n",
        );
        let sets = read_caliscope_timestamps(&path).expect("parses");
        assert_eq!(sets.len(), 3);
        assert_eq!(sets[0].sync_index, 26);
        assert_eq!(sets[0].frames[&0], (0, 10.0));
        assert_eq!(sets[0].frames[&1], (0, 10.001));
        assert_eq!(sets[1].frames[&1], (1, 10.2));
        // Camera 0 skipped a capture index: its video position follows frame_index.
        assert_eq!(sets[2].frames[&0], (3, 10.5));
        assert!(!sets[2].frames.contains_key(&1), "camera 1 has no frame in set 28");
    }

    #[test]
    fn caliscope_rows_without_frame_index_take_video_order() {
        let (_d, path) = write("sync_index,cam_id,frame_time\n5,0,1.0\n5,1,1.01\n6,1,1.2\n7,0,1.4\n7,1,1.41\n");
        let sets = read_caliscope_timestamps(&path).expect("parses");
        assert_eq!(sets.len(), 3);
        assert_eq!(sets[2].frames[&0], (1, 1.4), "camera 0's second row is its video's second frame");
        assert_eq!(sets[2].frames[&1], (2, 1.41));
    }

    #[test]
    fn rows_without_sync_index_are_grouped_by_capture_time() {
        // Older caliscope: `port`; camera 1 drops the frame near 1.2 s.
        let (_d, path) = write(
            "port,frame_index,frame_time\n0,0,1.00\n1,0,1.02\n0,1,1.20\n0,2,1.40\n1,1,1.41\n0,3,1.60\n1,2,1.58\n",
        );
        let sets = read_caliscope_timestamps(&path).expect("parses");
        assert_eq!(sets.len(), 4);
        assert_eq!(sets[0].frames[&1], (0, 1.02));
        assert!(!sets[1].frames.contains_key(&1), "camera 1 has no frame near 1.2 s");
        assert_eq!(sets[2].frames[&1], (1, 1.41));
        assert_eq!(sets[3].frames[&0], (3, 1.60));
        assert_eq!(sets[3].frames[&1], (2, 1.58));
    }

    #[test]
    fn bad_caliscope_files_name_the_line() {
        let (_d, p) = write("sync,cam,time\n");
        assert!(read_caliscope_timestamps(&p).unwrap_err().to_string().contains("sync_index"));
        let (_d, p) = write("sync_index,cam_id,frame_time\n1,0,abc\n");
        let e = read_caliscope_timestamps(&p).unwrap_err().to_string();
        assert!(e.contains("line 2") && e.contains("abc"), "{e}");
        let (_d, p) = write("sync_index,cam_id,frame_time\n1,0,1.0\n1,0,1.1\n");
        let e = read_caliscope_timestamps(&p).unwrap_err().to_string();
        assert!(e.contains("line 3") && e.contains("twice"), "{e}");
        let (_d, p) = write("sync_index,cam_id,frame_index,frame_time\n1,0,5,1.0\n2,0,4,1.1\n");
        let e = read_caliscope_timestamps(&p).unwrap_err().to_string();
        assert!(e.contains("line 3") && e.contains("does not follow"), "{e}");
        let (_d, p) = write("sync_index,cam_id,frame_time\n");
        assert!(read_caliscope_timestamps(&p).unwrap_err().to_string().contains("no frame"));
    }
}
