//! Matching a rig's camera names with the names other tools give the same cameras: video
//! files (`cam_0.mp4`), Pose2Sim folders (`cam01_json`), a reference file's camera list.
//!
//! The rules, tried in order, each for the whole rig at once (a rig is never matched half
//! by one rule and half by another, so that one odd name cannot shift the others):
//! 1. **Exact name**, an item's extension stripped first (`cam_0.mp4` is `cam_0`).
//! 2. **Camera number**: the last run of digits in each name, compared as integers, so
//!    `cam1`, `cam01`, `cam_1` and `cam01_json` are all camera 1 (caliscope's camera N is
//!    `cam_N`). Items whose number no rig camera has are ignored; two items with a number a
//!    rig camera needs are ambiguous and refused.
//! 3. **Shifted numbering**: when every rig camera and every item has a number, there are as
//!    many items as cameras, and the item numbers are the rig numbers plus one constant
//!    (Pose2Sim numbers `cam01..cam04` what caliscope calls `cam_0..cam_3`), camera and item
//!    are matched in order. A constant shift is required, rather than any one-to-one order,
//!    so that numbers with gaps on one side only (`cam_0, cam_2` against `cam1, cam2`) are
//!    refused instead of guessed.
//!
//! Anything else is an error that lists both sides.

/// For each of `rig_names`, the index in `found` of the same camera, by the rules of the
/// [module documentation](self); an error naming both lists when no rule matches every
/// camera.
pub fn match_cameras(rig_names: &[String], found: &[String]) -> Result<Vec<usize>, String> {
    if let Some(matched) = match_exactly(rig_names, found) {
        return Ok(matched);
    }
    let rig_numbers: Vec<Option<u64>> = rig_names.iter().map(|n| camera_number(n)).collect();
    let found_numbers: Vec<Option<u64>> = found.iter().map(|n| camera_number(strip_extension(n))).collect();
    let by_number = match_by_number(&rig_numbers, &found_numbers);
    let by_number = match by_number {
        Ok(matched) => return Ok(matched),
        Err(why) => why,
    };
    if let Some(matched) = match_by_shift(&rig_numbers, &found_numbers) {
        return Ok(matched);
    }
    Err(format!(
        "cannot match the rig's cameras [{}] with [{}]: no exact names, and by camera number: {by_number}",
        rig_names.join(", "),
        found.join(", ")
    ))
}

/// `name` without a file extension: `cam_0.mp4` is `cam_0`. Only an extension that starts
/// with a letter counts, so a dotted number (`cam.1`) keeps its digits.
pub fn strip_extension(name: &str) -> &str {
    match name.rsplit_once('.') {
        Some((stem, ext))
            if !stem.is_empty()
                && ext.len() <= 8
                && ext.starts_with(|c: char| c.is_ascii_alphabetic())
                && ext.chars().all(|c| c.is_ascii_alphanumeric()) =>
        {
            stem
        }
        _ => name,
    }
}

/// The camera number in a name: its last run of ASCII digits as an integer (`cam01_json`
/// is 1), `None` without digits or when the run does not fit in a `u64`.
pub fn camera_number(name: &str) -> Option<u64> {
    let end = name.rfind(|c: char| c.is_ascii_digit())? + 1;
    // After the last character that is not a digit, whatever its width (`caméra1`).
    let start =
        name[..end].char_indices().rev().find(|(_, c)| !c.is_ascii_digit()).map_or(0, |(i, c)| i + c.len_utf8());
    name[start..end].parse().ok()
}

fn match_exactly(rig_names: &[String], found: &[String]) -> Option<Vec<usize>> {
    rig_names
        .iter()
        .map(|name| {
            let mut hits = found.iter().enumerate().filter(|(_, f)| f.as_str() == name || strip_extension(f) == name);
            let first = hits.next()?.0;
            // `cam_0` and `cam_0.mp4` side by side: not this rule's to decide.
            hits.next().is_none().then_some(first)
        })
        .collect()
}

fn match_by_number(rig_numbers: &[Option<u64>], found_numbers: &[Option<u64>]) -> Result<Vec<usize>, String> {
    let mut matched = Vec::with_capacity(rig_numbers.len());
    for (c, number) in rig_numbers.iter().enumerate() {
        let Some(number) = number else { return Err(format!("rig camera {c} has no number in its name")) };
        if rig_numbers.iter().filter(|n| **n == Some(*number)).count() > 1 {
            return Err(format!("two rig cameras have the number {number}"));
        }
        let hits: Vec<usize> = (0..found_numbers.len()).filter(|&i| found_numbers[i] == Some(*number)).collect();
        match hits.as_slice() {
            [one] => matched.push(*one),
            [] => return Err(format!("nothing has the number {number}")),
            _ => return Err(format!("{} items have the number {number}", hits.len())),
        }
    }
    Ok(matched)
}

fn match_by_shift(rig_numbers: &[Option<u64>], found_numbers: &[Option<u64>]) -> Option<Vec<usize>> {
    if rig_numbers.is_empty() || rig_numbers.len() != found_numbers.len() {
        return None;
    }
    let rig: Vec<u64> = rig_numbers.iter().copied().collect::<Option<_>>()?;
    let items: Vec<u64> = found_numbers.iter().copied().collect::<Option<_>>()?;
    let mut rig_order: Vec<usize> = (0..rig.len()).collect();
    rig_order.sort_by_key(|&c| rig[c]);
    let mut item_order: Vec<usize> = (0..items.len()).collect();
    item_order.sort_by_key(|&i| items[i]);
    let shift = i128::from(items[item_order[0]]) - i128::from(rig[rig_order[0]]);
    let mut matched = vec![0; rig.len()];
    for (k, (&c, &i)) in rig_order.iter().zip(&item_order).enumerate() {
        // Sorted and shifted by one constant, and no number twice on either side.
        let repeated = k > 0 && (rig[c] == rig[rig_order[k - 1]] || items[i] == items[item_order[k - 1]]);
        if repeated || i128::from(items[i]) - i128::from(rig[c]) != shift {
            return None;
        }
        matched[c] = i;
    }
    Some(matched)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(list: &[&str]) -> Vec<String> {
        list.iter().map(|s| (*s).to_owned()).collect()
    }

    #[test]
    fn exact_names_match_in_any_order_and_with_an_extension() {
        let rig = names(&["cam_0", "cam_1", "cam_2"]);
        assert_eq!(match_cameras(&rig, &names(&["cam_2", "cam_0", "cam_1"])), Ok(vec![1, 2, 0]));
        assert_eq!(
            match_cameras(&rig, &names(&["cam_1.mp4", "cam_2.mp4", "cam_0.mp4", "notes.txt"])),
            Ok(vec![2, 0, 1])
        );
        let named = names(&["left", "right"]);
        assert_eq!(match_cameras(&named, &names(&["right.avi", "left.avi"])), Ok(vec![1, 0]));
    }

    #[test]
    fn numbers_match_as_integers_whatever_the_padding() {
        let rig = names(&["cam_1", "cam_2", "cam_10"]);
        assert_eq!(match_cameras(&rig, &names(&["cam10_json", "cam01_json", "cam2_json"])), Ok(vec![1, 2, 0]));
        // Items with numbers no camera has are left over, not an error.
        let rig = names(&["cam_0", "cam_1"]);
        assert_eq!(match_cameras(&rig, &names(&["cam1", "cam0", "cam7"])), Ok(vec![1, 0]));
    }

    #[test]
    fn pose2sim_numbering_from_one_matches_a_rig_numbered_from_zero_by_shift() {
        let rig = names(&["cam_0", "cam_1", "cam_2", "cam_3"]);
        let pose2sim = names(&["cam03_json", "cam01_json", "cam04_json", "cam02_json"]);
        assert_eq!(match_cameras(&rig, &pose2sim), Ok(vec![1, 3, 0, 2]));
    }

    #[test]
    fn refuses_ambiguity_and_gaps_listing_both_sides() {
        let rig = names(&["cam_0", "cam_2"]);
        // Not one constant shift: 0 -> 1 but 2 -> 2.
        let err = match_cameras(&rig, &names(&["cam1", "cam2"])).unwrap_err();
        assert!(err.contains("cam_0, cam_2") && err.contains("cam1, cam2"), "{err}");
        // Two items say camera 1.
        let err = match_cameras(&names(&["cam_1"]), &names(&["cam1", "cam01"])).unwrap_err();
        assert!(err.contains("2 items have the number 1"), "{err}");
        // No numbers, no names in common.
        let err = match_cameras(&names(&["left", "right"]), &names(&["front", "side"])).unwrap_err();
        assert!(err.contains("left, right") && err.contains("front, side"), "{err}");
        // A camera missing altogether.
        assert!(match_cameras(&names(&["cam_0", "cam_1", "cam_2"]), &names(&["cam_0", "cam_1"])).is_err());
    }

    #[test]
    fn camera_numbers_and_extensions() {
        assert_eq!(camera_number("cam01_json"), Some(1));
        assert_eq!(camera_number("cam_12"), Some(12));
        assert_eq!(camera_number("front"), None);
        // A name with letters wider than a byte before its number (found by fuzzing).
        assert_eq!(camera_number("caméra1"), Some(1));
        assert_eq!(camera_number("cam_é12"), Some(12));
        assert_eq!(camera_number("é"), None);
        assert_eq!(strip_extension("cam_0.mp4"), "cam_0");
        assert_eq!(strip_extension("cam.1"), "cam.1");
        assert_eq!(strip_extension(".hidden"), ".hidden");
    }
}
