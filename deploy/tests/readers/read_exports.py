#!/usr/bin/env python3
"""Reads handflow's exports with readers that share no code with it, and prints what they
hold as JSON: TRC by OpenSim's layout (five header lines, tab-separated, blank fields are
missing markers), C3D with the `c3d` package from PyPI, CSV with Python's csv module.

Usage: read_exports.py [--trc FILE] [--c3d FILE] [--csv FILE]
"""
import argparse
import csv
import json


def read_trc(path):
    with open(path, newline="") as f:
        lines = f.read().split("\n")
    assert lines[0].startswith("PathFileType\t4\t(X/Y/Z)"), lines[0]
    keys = lines[1].split("\t")
    values = lines[2].split("\t")
    header = dict(zip(keys, values))
    names = [n for n in lines[3].split("\t")[2:] if n]
    axes = lines[4].split("\t")[2:]
    assert axes[: 3 * len(names)] == [f"{a}{k}" for k in range(1, len(names) + 1) for a in "XYZ"], axes
    frames = []
    for line in lines[6:]:
        if not line:
            continue
        fields = line.split("\t")
        assert len(fields) == 2 + 3 * len(names), line
        markers = {}
        for k, name in enumerate(names):
            xyz = fields[2 + 3 * k: 5 + 3 * k]
            markers[name] = None if all(v == "" for v in xyz) else [float(v) for v in xyz]
        frames.append({"frame": int(fields[0]), "time": float(fields[1]), "markers": markers})
    return {
        "rate": float(header["DataRate"]),
        "camera_rate": float(header["CameraRate"]),
        "frames_declared": int(header["NumFrames"]),
        "markers_declared": int(header["NumMarkers"]),
        "units": header["Units"],
        "first_frame": int(header["OrigDataStartFrame"]),
        "names": names,
        "frames": frames,
    }


def read_c3d(path):
    import c3d

    with open(path, "rb") as f:
        reader = c3d.Reader(f)
        labels = [label.strip() for label in reader.point_labels]
        units = reader.get("POINT:UNITS").string_value.strip()
        frames = []
        for number, points, _analog in reader.read_frames():
            markers = {}
            for label, p in zip(labels, points):
                valid = p[3] >= 0
                markers[label] = {"position": [float(v) for v in p[:3]] if valid else None, "residual": float(p[3])}
            frames.append({"frame": int(number), "markers": markers})
        return {
            "rate": float(reader.point_rate),
            "scale": float(reader.point_scale),
            "labels": labels,
            "units": units,
            "first_frame": int(reader.first_frame),
            "last_frame": int(reader.last_frame),
            "frames": frames,
        }


def read_csv(path):
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    return {"columns": list(rows[0].keys()) if rows else [], "rows": rows}


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--trc")
    parser.add_argument("--c3d")
    parser.add_argument("--csv")
    args = parser.parse_args()
    out = {}
    if args.trc:
        out["trc"] = read_trc(args.trc)
    if args.c3d:
        out["c3d"] = read_c3d(args.c3d)
    if args.csv:
        out["csv"] = read_csv(args.csv)
    print(json.dumps(out, allow_nan=False))


if __name__ == "__main__":
    main()
