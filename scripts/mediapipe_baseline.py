#!/usr/bin/env python3
"""The pipeline a user would pick instead of handflow, as caliscope and FreeMoCap run it:
MediaPipe Holistic on every view, then triangulation. Measures its speed on a recording folder.

    python3 scripts/mediapipe_baseline.py RECORDING [--frames N] [--json] [--out FILE]

Needs `mediapipe` (0.10.14, whose wheel bundles the Holistic models) and OpenCV;
scripts/mediapipe_baseline.sh makes a virtualenv with both and runs this beside `handflow track`.

RECORDING holds one video per camera (mp4, mkv, avi, mov, webm; in the folder or its `videos/`)
and a calibration: `camera_array.toml` or `rig.toml`, else the only `.toml` file of the folder or
of its `calibration/` folder, in caliscope's layout (`[cameras.N]` tables, camera N named
`cam_N`) or anipose's / Pose2Sim's (one table per camera, named by its `name`, else its key).
Videos are matched to cameras as `handflow track` matches them: by name (`cam_0.mp4` is camera
`cam_0`), else by the last number in the names (`cam01.mp4` is `cam_1`). Frame k of every video
is frame set k: caliscope's `timestamps.csv` is not read, so a video missing frames would put
its camera out of step.

Per camera one Holistic tracker (`static_image_mode=False`, `model_complexity=1`), as caliscope
keeps one per camera, each camera decoded and tracked in its own thread. Per frame set and view:
the palm centre of each hand (mean of hand landmarks 0, 5, 9, 13, 17: the wrist and the four
knuckles; Holistic's left hand is the person's left) and the head (midpoint of the ears, pose
landmarks 7 and 8). Each object seen by two views or more is triangulated (linear DLT on the
undistorted, normalised points). Frames go to MediaPipe as the videos store them.

Reports frame sets per second, the wall clock from opening the videos to the last triangulated
frame set (the trackers' model loading, decoding and triangulation included; Python's start-up
and imports not), and per object the number of frame sets it was triangulated in. `--out FILE`
writes per frame set a JSON line with each triangulated object's 3D point (calibration's world
frame, metres), its 2D points (pixels) and their mean reprojection error. `--openpose DIR` writes
each view's landmarks as OpenPose would (one folder per camera, one `*_keypoints.json` per frame):
the body in BODY_25's order (a landmark MediaPipe rates under 0.5 visible left out, confidence 0,
as OpenPose leaves out what it does not see) and each hand's 21 landmarks in
`hand_left_keypoints_2d` / `hand_right_keypoints_2d` (confidence 1; 63 zeros for a hand not
found, as OpenPose run with `--hand` writes), so `handflow eval tracks --reference DIR` can be
checked against this reference in OpenPose's form.
"""

import argparse
import json
import re
import sys
import time
import tomllib
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

try:
    import cv2
    import mediapipe as mp
    import numpy as np
except ImportError as error:
    sys.exit(
        f"mediapipe_baseline: {error.name} is not installed; scripts/mediapipe_baseline.sh makes a "
        "virtualenv with mediapipe 0.10.14 and OpenCV"
    )

VIDEO_EXTENSIONS = {".mp4", ".mkv", ".avi", ".mov", ".webm"}
CALIBRATION_NAMES = ("camera_array.toml", "rig.toml")
OBJECTS = ("head", "left_hand", "right_hand")
PALM_LANDMARKS = (0, 5, 9, 13, 17)
LEFT_EAR, RIGHT_EAR = 7, 8
# BODY_25 keypoint -> MediaPipe pose landmark, for `--openpose`: nose, right shoulder, elbow,
# wrist, left shoulder, elbow, wrist, right hip, left hip, right eye, left eye, right ear, left ear.
BODY_25_FROM_MEDIAPIPE = {0: 0, 2: 12, 3: 14, 4: 16, 5: 11, 6: 13, 7: 15, 9: 24, 12: 23, 15: 5, 16: 2, 17: 8, 18: 7}
HAND_LANDMARKS = 21
MIN_VISIBILITY = 0.5
# Encoders pad frame sizes to multiples of 16: a video this much off its calibration's size is
# the same image (handflow accepts it too); more is another resolution, which would need the
# intrinsics scaled.
MAX_PADDING_PX = 15


class BaselineError(Exception):
    """A problem with the recording, reported as one line."""


@dataclass
class Camera:
    name: str
    size: tuple  # (width, height), pixels
    matrix: np.ndarray  # K, 3x3
    distortions: np.ndarray  # k1 k2 p1 p2 [k3]
    rvec: np.ndarray  # world to camera, Rodrigues
    translation: np.ndarray  # world to camera, metres
    video: Path | None = None  # set by match_videos

    def projection(self):
        """[R | t]: projects world points to normalised (undistorted, K removed) coordinates."""
        rotation, _ = cv2.Rodrigues(self.rvec)
        return np.hstack([rotation, self.translation.reshape(3, 1)])


# --- Calibration ---------------------------------------------------------------------------


def find_calibration(recording):
    for name in CALIBRATION_NAMES:
        if (recording / name).is_file():
            return recording / name
    for folder in (recording, recording / "calibration"):
        tomls = sorted(folder.glob("*.toml")) if folder.is_dir() else []
        if len(tomls) == 1:
            return tomls[0]
        if len(tomls) > 1:
            raise BaselineError(
                f"{folder}: several calibration files ({', '.join(p.name for p in tomls)}); "
                f"name the one to use {' or '.join(CALIBRATION_NAMES)}"
            )
    raise BaselineError(
        f"{recording}: no calibration ({' or '.join(CALIBRATION_NAMES)}, or one .toml file here or in calibration/)"
    )


def read_calibration(path):
    """The cameras of a caliscope or anipose / Pose2Sim TOML file, in the file's order (caliscope's by N)."""
    try:
        root = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as error:
        raise BaselineError(f"{path}: not TOML: {error}") from None
    cameras_table = root.get("cameras")
    # caliscope: a `cameras` table of `[cameras.N]` tables (an anipose camera table named
    # `cameras` would have a `matrix` of its own).
    if isinstance(cameras_table, dict) and "matrix" not in cameras_table:
        # In the order of N as a number ("10" after "2").
        entries = sorted(cameras_table.items(), key=lambda item: (not item[0].isdigit(), len(item[0]), item[0]))
        tables = [(f"cameras.{key}", f"cam_{key}", table) for key, table in entries]
    else:
        # anipose / Pose2Sim: every table with a `matrix` is a camera (`[metadata]` is not), named
        # by its `name`, else by its key (caliscope's older `[cam_N]` tables).
        tables = [
            (key, table.get("name", key), table)
            for key, table in root.items()
            if isinstance(table, dict) and "matrix" in table
        ]
    cameras = []
    for key, name, table in tables:
        if not isinstance(table, dict):
            raise BaselineError(f"{path}: [{key}] is not a table")
        # caliscope's `ignore = true` switches a camera off.
        if not table.get("ignore", False):
            cameras.append(camera_from_table(path, key, name, table))
    if len(cameras) < 2:
        raise BaselineError(f"{path}: {len(cameras)} camera(s) found, triangulation needs two or more")
    return cameras


def camera_from_table(path, key, name, table):
    def field(field_name, shape):
        if field_name not in table:
            raise BaselineError(f"{path}: camera table [{key}] has no `{field_name}`")
        try:
            value = np.asarray(table[field_name], dtype=np.float64)
        except (TypeError, ValueError):
            value = None
        if value is None or value.shape not in shape:
            expected = " or ".join(
                f"{s[0]} numbers" if len(s) == 1 else f"{s[0]} rows of {s[1]} numbers" for s in shape
            )
            raise BaselineError(f"{path}: [{key}] `{field_name}` should be {expected}, found {table[field_name]!r}")
        return value

    rotation = field("rotation", [(3,), (3, 3)])
    if rotation.shape == (3, 3):
        # caliscope writes the matrix; anipose and Pose2Sim a Rodrigues vector.
        rotation, _ = cv2.Rodrigues(rotation)
    width, height = field("size", [(2,)])
    return Camera(
        name=str(name),
        size=(int(width), int(height)),
        matrix=field("matrix", [(3, 3)]),
        distortions=field("distortions", [(4,), (5,)]),
        rvec=rotation.reshape(3),
        translation=field("translation", [(3,)]),
    )


# --- Videos --------------------------------------------------------------------------------


def last_number(name):
    numbers = re.findall(r"\d+", name)
    return int(numbers[-1]) if numbers else None


def match_videos(recording, cameras):
    """Sets each camera's video: every camera by its exact name, else every one by its number."""
    folder = recording
    videos = [p for p in sorted(folder.iterdir()) if p.suffix.lower() in VIDEO_EXTENSIONS]
    if not videos and (recording / "videos").is_dir():
        folder = recording / "videos"
        videos = [p for p in sorted(folder.iterdir()) if p.suffix.lower() in VIDEO_EXTENSIONS]
    if not videos:
        raise BaselineError(f"{recording}: no video ({', '.join(sorted(VIDEO_EXTENSIONS))}) here or in videos/")
    by_name = {p.stem: p for p in videos}
    if all(c.name in by_name for c in cameras):
        for camera in cameras:
            camera.video = by_name[camera.name]
        return
    for camera in cameras:
        number = last_number(camera.name)
        hits = [p for p in videos if number is not None and last_number(p.stem) == number]
        if len(hits) != 1:
            raise BaselineError(
                f"{folder}: cannot match camera `{camera.name}` with a video "
                f"({'none' if not hits else 'several'} of {', '.join(p.name for p in videos)} "
                f"has its name or its number {number})"
            )
        camera.video = hits[0]


def open_video(camera):
    capture = cv2.VideoCapture(str(camera.video))
    if not capture.isOpened():
        raise BaselineError(f"{camera.video}: OpenCV cannot open it as a video")
    size = (int(capture.get(cv2.CAP_PROP_FRAME_WIDTH)), int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT)))
    if any(abs(v - c) > MAX_PADDING_PX for v, c in zip(size, camera.size)):
        raise BaselineError(
            f"{camera.video}: {size[0]}x{size[1]}, but camera `{camera.name}` is calibrated at "
            f"{camera.size[0]}x{camera.size[1]}"
        )
    return capture


# --- Landmarks and triangulation -------------------------------------------------------------


def observe(capture, tracker, keypoints=None):
    """The next frame's objects in pixels ({name: (x, y)}), or None at the end of the video.
    With `keypoints` (a dict), also puts there the view's OpenPose person (see `--openpose`)."""
    ok, frame = capture.read()
    if not ok:
        return None
    height, width = frame.shape[:2]
    results = tracker.process(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB))

    # MediaPipe's normalised coordinates span the image's edges (a pixel's centre at +0.5);
    # the calibration puts pixel (0, 0)'s centre at (0, 0), as OpenCV does.
    def pixels(landmarks, indices):
        return (
            width * np.mean([landmarks.landmark[i].x for i in indices]) - 0.5,
            height * np.mean([landmarks.landmark[i].y for i in indices]) - 0.5,
        )

    if keypoints is not None:
        keypoints.update(openpose_person(results, width, height))
    seen = {}
    if results.pose_landmarks is not None:
        seen["head"] = pixels(results.pose_landmarks, (LEFT_EAR, RIGHT_EAR))
    if results.left_hand_landmarks is not None:
        seen["left_hand"] = pixels(results.left_hand_landmarks, PALM_LANDMARKS)
    if results.right_hand_landmarks is not None:
        seen["right_hand"] = pixels(results.right_hand_landmarks, PALM_LANDMARKS)
    return seen


def openpose_person(results, width, height):
    """One view's Holistic landmarks as an OpenPose person: BODY_25 body and 21-point hands."""

    def pixel(landmark):
        return [round(width * landmark.x - 0.5, 2), round(height * landmark.y - 0.5, 2)]

    pose = [0.0] * (3 * 25)
    if results.pose_landmarks is not None:
        for keypoint, index in BODY_25_FROM_MEDIAPIPE.items():
            landmark = results.pose_landmarks.landmark[index]
            if landmark.visibility >= MIN_VISIBILITY:
                pose[3 * keypoint : 3 * keypoint + 3] = pixel(landmark) + [round(landmark.visibility, 3)]

    def hand(landmarks):
        if landmarks is None:
            return [0.0] * (3 * HAND_LANDMARKS)
        return [v for landmark in landmarks.landmark for v in pixel(landmark) + [1.0]]

    return {
        "pose_keypoints_2d": pose,
        "hand_left_keypoints_2d": hand(results.left_hand_landmarks),
        "hand_right_keypoints_2d": hand(results.right_hand_landmarks),
    }


def write_openpose(folder, camera, frame, person):
    path = folder / camera / f"{camera}_{frame:012d}_keypoints.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    people = [person] if any(person["pose_keypoints_2d"]) else []
    path.write_text(json.dumps({"version": 1.3, "people": people}))


def triangulate(cameras, projections, views):
    """The world point of one object seen by `views` ({camera index: (x, y) pixels})."""
    rows = []
    for index, pixel in views.items():
        camera = cameras[index]
        point = np.array([[pixel]], dtype=np.float64)
        x, y = cv2.undistortPoints(point, camera.matrix, camera.distortions).reshape(2)
        projection = projections[index]
        rows.append(x * projection[2] - projection[0])
        rows.append(y * projection[2] - projection[1])
    # The homogeneous point is the right singular vector of the smallest singular value.
    homogeneous = np.linalg.svd(np.array(rows))[2][-1]
    return homogeneous[:3] / homogeneous[3]


def reprojection_px(cameras, point, views):
    errors = []
    for index, pixel in views.items():
        camera = cameras[index]
        projected, _ = cv2.projectPoints(
            point.reshape(1, 3), camera.rvec, camera.translation, camera.matrix, camera.distortions
        )
        errors.append(np.linalg.norm(projected.reshape(2) - np.asarray(pixel)))
    return float(np.mean(errors))


# --- The run ---------------------------------------------------------------------------------


def run(recording, frames, out, openpose=None):
    calibration = find_calibration(recording)
    cameras = read_calibration(calibration)
    match_videos(recording, cameras)
    projections = [camera.projection() for camera in cameras]
    triangulated = dict.fromkeys(OBJECTS, 0)
    frame_sets = 0

    start = time.perf_counter()
    captures = [open_video(camera) for camera in cameras]
    trackers = [mp.solutions.holistic.Holistic(static_image_mode=False, model_complexity=1) for _ in cameras]
    # One thread per camera: OpenCV's decoding and MediaPipe's graph release the GIL, so the
    # views are tracked in parallel as in caliscope, where each camera's stream has its own
    # thread. Each camera's capture and tracker are only ever used by one task at a time.
    with ThreadPoolExecutor(len(cameras)) as pool:
        while frames is None or frame_sets < frames:
            people = [{} if openpose is not None else None for _ in cameras]
            seen = list(pool.map(observe, captures, trackers, people))
            if any(s is None for s in seen):
                break
            if openpose is not None:
                for camera, person in zip(cameras, people):
                    write_openpose(openpose, camera.name, frame_sets, person)
            record = {"frame": frame_sets, "objects": {}}
            for name in OBJECTS:
                views = {i: s[name] for i, s in enumerate(seen) if name in s}
                if len(views) < 2:
                    continue
                point = triangulate(cameras, projections, views)
                triangulated[name] += 1
                if out is not None:
                    record["objects"][name] = {
                        "3d": [round(float(v), 5) for v in point],
                        "2d": {cameras[i].name: [round(float(v), 2) for v in p] for i, p in views.items()},
                        "reprojection_px": round(reprojection_px(cameras, point, views), 2),
                    }
            if out is not None:
                out.write(json.dumps(record) + "\n")
            frame_sets += 1
    seconds = time.perf_counter() - start
    for capture, tracker in zip(captures, trackers):
        capture.release()
        tracker.close()
    if frame_sets == 0:
        raise BaselineError(f"{recording}: a video has no frame")
    return {
        "recording": str(recording),
        "calibration": str(calibration),
        "cameras": [camera.name for camera in cameras],
        "videos": [camera.video.name for camera in cameras],
        "mediapipe": mp.__version__,
        "frame_sets": frame_sets,
        "seconds": seconds,
        "frame_sets_per_second": frame_sets / seconds,
        "triangulated": triangulated,
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("recording", type=Path, help="recording folder: one video per camera and a calibration")
    parser.add_argument("--frames", type=int, help="read at most N frame sets")
    parser.add_argument("--json", action="store_true", help="print the report as one JSON object")
    parser.add_argument("--out", type=Path, help="write the triangulated points as JSON Lines")
    parser.add_argument("--openpose", type=Path, help="write each view's landmarks as OpenPose JSON into this folder")
    args = parser.parse_args()
    if args.frames is not None and args.frames < 1:
        parser.error("--frames must be at least 1")
    if not args.recording.is_dir():
        sys.exit(f"mediapipe_baseline: recording folder {args.recording} not found")
    try:
        if args.out is None:
            report = run(args.recording, args.frames, None, args.openpose)
        else:
            with open(args.out, "w") as out:
                report = run(args.recording, args.frames, out, args.openpose)
    except BaselineError as error:
        sys.exit(f"mediapipe_baseline: {error}")
    if args.json:
        print(json.dumps(report))
        return
    n = report["frame_sets"]
    print(
        f"{report['recording']}: {len(report['cameras'])} cameras ({', '.join(report['videos'])}), "
        f"calibration {report['calibration']}"
    )
    print(
        f"MediaPipe {report['mediapipe']} Holistic per view + triangulation: {n} frame sets in "
        f"{report['seconds']:.1f} s, {report['frame_sets_per_second']:.2f} frame sets/s"
    )
    print("triangulated: " + ", ".join(f"{name} in {count} of {n}" for name, count in report["triangulated"].items()))


if __name__ == "__main__":
    main()
