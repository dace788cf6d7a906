#!/usr/bin/env python3
"""Independent check of a dataset written by `nori record` against LeRobot's v3.0 layout.

Reads the dataset with pyarrow/pandas/numpy only (no code of this repository), the way LeRobot
does (`lerobot/datasets/utils.py`: `load_info`, `load_nested_dataset` over `data/*/*.parquet`,
`load_episodes` over `meta/episodes/*/*.parquet`, `pd.read_parquet(meta/tasks.parquet)`,
`load_stats`), and checks field names, schema, row counts, indices, timestamps and statistics.
Videos (`dtype: video` features) are decoded with PyAV, as LeRobot's `pyav` backend decodes them:
every episode's frames are where its `videos/<key>/from_timestamp..to_timestamp` says, one per
data frame at `from + k / fps`, of the feature's size, and the image statistics are those of the
decoded pictures.

Usage: check_lerobot_dataset.py ROOT [--episodes N] [--in-flight] [--closed]

--in-flight accepts what a recorder killed during a commit leaves before the next start repairs
it: `info.json` (written last) may not count the one episode being committed, whose row may
already be in the episode table and whose frames may already be in the data file.
--closed: the recorder exited cleanly, so nothing of its own (`.nori-staging`) may be left.
Prints a JSON summary on success; exits 1 with the reason on the first failure, 3 if pyarrow,
pandas or numpy (or, for a dataset with videos, PyAV) cannot be imported.
"""
import json
import math
import sys
from pathlib import Path

try:
    import numpy as np
    import pandas as pd
    import pyarrow as pa
    import pyarrow.parquet as pq
except ImportError as e:  # the Rust test decides whether that is a skip or a failure
    print(f"cannot import: {e}", file=sys.stderr)
    sys.exit(3)

# The order LeRobot 0.6 writes (its DatasetInfo dataclass, serialised field by field).
INFO_KEYS = [
    "codebase_version", "fps", "features", "total_episodes", "total_frames", "total_tasks", "chunks_size",
    "data_files_size_in_mb", "video_files_size_in_mb", "data_path", "video_path", "robot_type", "splits",
]
DEFAULT_FEATURES = {
    "timestamp": {"dtype": "float32", "shape": [1], "names": None},
    "frame_index": {"dtype": "int64", "shape": [1], "names": None},
    "episode_index": {"dtype": "int64", "shape": [1], "names": None},
    "index": {"dtype": "int64", "shape": [1], "names": None},
    "task_index": {"dtype": "int64", "shape": [1], "names": None},
}
DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
VIDEO_INFO_KEYS = ["video.height", "video.width", "video.codec", "video.pix_fmt", "video.is_depth_map",
                   "video.fps", "video.channels", "has_audio"]
STATS = ["min", "max", "mean", "std", "count", "q01", "q10", "q50", "q90", "q99"]
QUANTILES = {"q01": 0.01, "q10": 0.10, "q50": 0.50, "q90": 0.90, "q99": 0.99}
REQUIRED = ["observation.state", "observation.current", "action", "observation.joint_valid"]


def fail(msg):
    print(f"LeRobot check failed: {msg}", file=sys.stderr)
    sys.exit(1)


def check(cond, msg):
    if not cond:
        fail(msg)


def close(a, b, what, rtol=1e-5, atol=1e-5):
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    check(a.shape == b.shape, f"{what}: shape {a.shape} vs {b.shape}")
    check(np.allclose(a, b, rtol=rtol, atol=atol, equal_nan=True), f"{what}: {a.tolist()} vs {b.tolist()}")


def column_array(table, key, spec):
    col = table.column(key)
    if spec["shape"] == [1]:
        # LeRobot maps shape (1,) to a scalar Value: a plain column, not a list.
        want = pa.float32() if spec["dtype"] == "float32" else pa.int64()
        check(col.type == want, f"data column {key}: type {col.type}, info.json says scalar {spec['dtype']}")
        return np.array(col.to_pylist(), dtype=np.float32 if spec["dtype"] == "float32" else np.int64)
    t = col.type
    check(pa.types.is_list(t) or pa.types.is_fixed_size_list(t), f"data column {key}: type {t} is not a list")
    check(t.value_type == pa.float32(), f"data column {key}: element type {t.value_type}, info.json says float32")
    values = col.to_pylist()
    check(all(v is not None and len(v) == spec["shape"][0] for v in values), f"data column {key}: a row is not of length {spec['shape'][0]}")
    return np.array(values, dtype=np.float32).reshape(len(values), spec["shape"][0])


def decode_episode(path, start, stop, fps):
    """RGB frames of the video at `path` whose times fall in [start, stop), with their times."""
    try:
        import av
    except ImportError as e:
        print(f"cannot import: {e} (pip install av)", file=sys.stderr)
        sys.exit(3)
    frames, times = [], []
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        for frame in container.decode(stream):
            t = float(frame.pts * stream.time_base)
            if start - 1e-4 <= t < stop - 1e-4:
                frames.append(frame.to_ndarray(format="rgb24"))
                times.append(t)
    return frames, times


def image_stats(frames):
    """LeRobot's image statistics of sampled frames (compute_stats.py): frames evenly sampled,
    shrunk by an integer stride to about 150 px, per channel over [0, 1], shaped (3, 1, 1)."""
    n = len(frames)
    k = max(min(n, 100), min(int(n ** 0.75), 10_000))
    idx = np.round(np.linspace(0, n - 1, k)).astype(int)
    h, w = frames[0].shape[:2]
    f = 1 if max(h, w) < 300 else (w // 150 if w > h else h // 150)
    x = np.stack([frames[i][::f, ::f, :] for i in idx]).astype(np.float64) / 255.0
    return {"mean": x.mean(axis=(0, 1, 2)), "std": x.std(axis=(0, 1, 2)),
            "min": x.min(axis=(0, 1, 2)), "max": x.max(axis=(0, 1, 2))}


def stats_of(x):
    """LeRobot's per-feature stats, exact, over finite values; x is (frames, width)."""
    x = x.astype(np.float64)
    with np.errstate(all="ignore"):
        import warnings
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            out = {
                "min": np.nanmin(x, axis=0), "max": np.nanmax(x, axis=0),
                "mean": np.nanmean(x, axis=0), "std": np.nanstd(x, axis=0),
                "count": np.array([len(x)]),
            }
            for k, q in QUANTILES.items():
                out[k] = np.nanquantile(x, q, axis=0)
    return out


def main():
    args = sys.argv[1:]
    check(args, "usage: check_lerobot_dataset.py ROOT [--episodes N] [--in-flight] [--closed]")
    root = Path(args[0])
    expect_episodes = int(args[args.index("--episodes") + 1]) if "--episodes" in args else None
    in_flight = "--in-flight" in args

    info = json.loads((root / "meta/info.json").read_text())
    check(list(info) == INFO_KEYS, f"info.json keys {list(info)} != LeRobot's {INFO_KEYS}")
    check(info["codebase_version"] == "v3.0", f"codebase_version {info['codebase_version']}")
    check(info["data_path"] == DATA_PATH, f"data_path {info['data_path']}")
    videos = {k: v for k, v in info["features"].items() if v["dtype"] == "video"}
    if videos:
        check(info["video_path"] == VIDEO_PATH, f"video_path {info['video_path']}, LeRobot's is {VIDEO_PATH}")
    else:
        check(info["video_path"] is None, "video_path should be null without videos")
    check(info["chunks_size"] == 1000, "chunks_size")
    check(info["video_files_size_in_mb"] == 200, f"video_files_size_in_mb {info['video_files_size_in_mb']}, LeRobot's default is 200")
    # Nothing of the recorder's is left in a dataset closed cleanly (push_to_hub would publish it).
    check("--closed" not in args or not (root / ".nori-staging").exists(), ".nori-staging left behind after a clean exit")
    fps = info["fps"]
    check(isinstance(fps, int) and fps > 0, f"fps {fps}")
    for k, spec in videos.items():
        check(k.startswith("observation.images."), f"video feature {k} outside observation.images.")
        check(list(spec) == ["dtype", "shape", "names", "info"], f"video feature {k}: keys {list(spec)}")
        check(spec["names"] == ["height", "width", "channels"], f"video feature {k}: names {spec['names']}")
        vi = spec["info"]
        check(list(vi) == VIDEO_INFO_KEYS, f"video feature {k}: info keys {list(vi)}")
        check(spec["shape"] == [vi["video.height"], vi["video.width"], vi["video.channels"]] and vi["video.channels"] == 3,
              f"video feature {k}: shape {spec['shape']} vs info {vi}")
        check(vi["video.fps"] == fps and vi["has_audio"] is False and vi["video.is_depth_map"] is False, f"video feature {k}: {vi}")
    features = {k: v for k, v in info["features"].items() if v["dtype"] != "video"}
    for k, v in DEFAULT_FEATURES.items():
        check(features.get(k) == v, f"feature {k}: {features.get(k)} != LeRobot's default {v}")
    for k in REQUIRED:
        check(k in features, f"feature {k} missing")
    for k, spec in features.items():
        check(set(spec) == {"dtype", "shape", "names"}, f"feature {k}: keys {sorted(spec)}")
        check("/" not in k, f"feature name {k} contains '/'")
        if k not in DEFAULT_FEATURES:
            check(spec["dtype"] == "float32" and len(spec["shape"]) == 1, f"feature {k}: {spec}")
            check(isinstance(spec["names"], list) and len(spec["names"]) == spec["shape"][0], f"feature {k}: names vs shape")
    check(features["observation.state"]["names"] == features["action"]["names"], "state and action name different joints")
    check(features["observation.joint_valid"]["names"] == features["observation.state"]["names"],
          "observation.joint_valid does not mark the state's dimensions")
    if expect_episodes is not None:
        check(info["total_episodes"] == expect_episodes, f"total_episodes {info['total_episodes']}, expected {expect_episodes}")
    check(info["splits"] == ({"train": f"0:{info['total_episodes']}"} if info["total_episodes"] else {}), f"splits {info['splits']}")

    # Tasks, as LeRobot loads them: the task text is the pandas index.
    tasks = pd.read_parquet(root / "meta/tasks.parquet")
    check(list(tasks.columns) == ["task_index"], f"tasks.parquet columns {list(tasks.columns)}")
    check(tasks.index.name == "task", f"tasks.parquet index named {tasks.index.name!r}, LeRobot's is 'task'")
    check(len(tasks) == info["total_tasks"] or (in_flight and len(tasks) == info["total_tasks"] + 1),
          f"{len(tasks)} tasks, info says {info['total_tasks']}")
    for text in tasks.index:
        check(isinstance(text, str) and text, f"task index entry {text!r}")
        check(int(tasks.loc[text].task_index) == list(tasks.index).index(text), f"task_index of {text!r}")

    # Episodes, as load_episodes reads them.
    ep_paths = sorted((root / "meta/episodes").glob("*/*.parquet"))
    check(ep_paths, "no episode file")
    episodes = pa.concat_tables([pq.read_table(p) for p in ep_paths]).to_pylist()
    extra_episode = len(episodes) - info["total_episodes"]
    check(extra_episode == 0 or (in_flight and extra_episode == 1), f"{len(episodes)} episode rows, info says {info['total_episodes']}")
    for col in ["episode_index", "tasks", "length", "data/chunk_index", "data/file_index", "dataset_from_index",
                "dataset_to_index", "meta/episodes/chunk_index", "meta/episodes/file_index"] + \
               [f"stats/{k}/{s}" for k in list(features) + list(videos) for s in STATS] + \
               [f"videos/{k}/{c}" for k in videos for c in ["chunk_index", "file_index", "from_timestamp", "to_timestamp"]]:
        check(col in episodes[0], f"episode table has no column {col}")

    # Frames, as load_nested_dataset reads them: every data/*/*.parquet, sorted, concatenated.
    data_paths = sorted((root / "data").glob("*/*.parquet"))
    check(data_paths, "no data file")
    tables = [pq.read_table(p) for p in data_paths]
    data = pa.concat_tables(tables)
    check(set(data.column_names) == set(features), f"data columns {data.column_names} != features {list(features)}")
    for k in ["frame_index", "episode_index", "index", "task_index"]:
        check(data.schema.field(k).type == pa.int64(), f"{k} is {data.schema.field(k).type}")
    check(data.schema.field("timestamp").type == pa.float32(), f"timestamp is {data.schema.field('timestamp').type}")
    for k, spec in features.items():
        if k in DEFAULT_FEATURES:
            continue
        t = data.schema.field(k).type
        want = pa.float32() if spec["shape"] == [1] else pa.list_(pa.field("element", pa.float32()), spec["shape"][0])
        check(t == want, f"{k} is {t}, LeRobot writes {want}")
    cols = {k: column_array(data, k, spec) for k, spec in features.items()}
    total = info["total_frames"]
    orphan_rows = data.num_rows - total
    check(orphan_rows == 0 or (in_flight and orphan_rows > 0), f"{data.num_rows} data rows, info says total_frames {total}")

    per_episode_stats = []
    expected_from = 0
    for i, ep in enumerate(episodes):
        check(ep["episode_index"] == i, f"episode row {i} has index {ep['episode_index']}")
        lo, hi, n = ep["dataset_from_index"], ep["dataset_to_index"], ep["length"]
        check(lo == expected_from and hi - lo == n and n > 0, f"episode {i}: {lo}..{hi} length {n}")
        expected_from = hi
        check(all(t in tasks.index for t in ep["tasks"]), f"episode {i} tasks {ep['tasks']}")
        path = root / DATA_PATH.format(chunk_index=ep["data/chunk_index"], file_index=ep["data/file_index"])
        t = pq.read_table(path)
        rows = t.filter(pa.compute.equal(t.column("episode_index"), i))
        check(rows.num_rows == n, f"episode {i}: {rows.num_rows} rows in {path.name}, length {n}")
        idx = rows.column("index").to_numpy()
        check((idx == np.arange(lo, hi)).all(), f"episode {i}: index not {lo}..{hi}")
        fi = rows.column("frame_index").to_numpy()
        check((fi == np.arange(n)).all(), f"episode {i}: frame_index not 0..{n}")
        ts = rows.column("timestamp").to_numpy()
        check(np.array_equal(ts, (np.arange(n) / fps).astype(np.float32)), f"episode {i}: timestamps are not frame_index / fps")
        ti = set(rows.column("task_index").to_pylist())
        check(ti == {int(tasks.loc[ep["tasks"][0]].task_index)}, f"episode {i}: task_index {ti}")
        ep_cols = {k: column_array(rows, k, spec) for k, spec in features.items()}
        mine = {}
        for k, spec in features.items():
            x = ep_cols[k].reshape(n, -1)
            want = stats_of(x)
            stored = {s: np.array(ep[f"stats/{k}/{s}"]) for s in STATS}
            for s in STATS:
                close(stored[s], want[s], f"episode {i} stats/{k}/{s}")
            mine[k] = stored
        for k, spec in videos.items():
            path = root / VIDEO_PATH.format(video_key=k, chunk_index=ep[f"videos/{k}/chunk_index"],
                                            file_index=ep[f"videos/{k}/file_index"])
            check(path.exists(), f"episode {i}: no video {path}")
            start, stop = ep[f"videos/{k}/from_timestamp"], ep[f"videos/{k}/to_timestamp"]
            check(abs((stop - start) - n / fps) < 1e-6, f"episode {i} {k}: spans {start}..{stop} for {n} frames")
            frames, times = decode_episode(path, start, stop, fps)
            check(len(frames) == n, f"episode {i} {k}: {len(frames)} frames decoded in {start}..{stop}, length {n}")
            check(np.allclose(times, start + np.arange(n) / fps, atol=1e-4), f"episode {i} {k}: frame times {times[:5]}...")
            check(frames[0].shape == tuple(spec["shape"]), f"episode {i} {k}: frames of {frames[0].shape}, feature {spec['shape']}")
            stored = {s: np.array(ep[f"stats/{k}/{s}"], dtype=object) for s in STATS}
            for s in STATS:
                if s != "count":
                    v = np.array(stored[s].tolist(), dtype=np.float64)
                    check(v.shape == (3, 1, 1), f"episode {i} stats/{k}/{s}: shape {v.shape}, LeRobot's is (3, 1, 1)")
                    check(((v >= 0) & (v <= 1)).all(), f"episode {i} stats/{k}/{s} outside [0, 1]: {v.ravel()}")
            want = image_stats(frames)
            for s in ["mean", "std"]:
                got = np.array(stored[s].tolist(), dtype=np.float64).ravel()
                # FFmpeg's and PyAV's YUV->RGB conversions may differ by a level or two.
                close(got, want[s], f"episode {i} stats/{k}/{s} vs the decoded frames", atol=0.02)
            mine[k] = {s: np.array(stored[s].tolist(), dtype=np.float64) for s in STATS}
        per_episode_stats.append(mine)

    # Global stats: min/max/mean/std/count over every committed frame, quantiles the
    # count-weighted average of the episodes' (LeRobot's aggregate_stats).
    check(episodes[info["total_episodes"] - 1]["dataset_to_index"] == total if total else True,
          f"info total_frames {total} is not where episode {info['total_episodes'] - 1} ends")
    stats = json.loads((root / "meta/stats.json").read_text())
    check(set(stats) == set(features) | set(videos), f"stats.json features {sorted(stats)}")
    for k in videos:
        check(list(stats[k]) == STATS, f"stats.json {k}: keys {list(stats[k])}")
        for s in STATS:
            v = np.array(stats[k][s], dtype=np.float64)
            check(v.shape == ((1,) if s == "count" else (3, 1, 1)), f"stats.json {k}/{s}: shape {v.shape}")
        counts = np.array([e[k]["count"][0] for e in per_episode_stats], dtype=np.float64)
        weighted = sum(e[k]["mean"] * c for e, c in zip(per_episode_stats, counts)) / counts.sum()
        close(np.array(stats[k]["mean"], dtype=np.float64), weighted, f"stats.json {k}/mean")
    # stats.json is written before info.json: in flight it may already count the new episode.
    covered = stats["index"]["count"][0]
    check(covered == total or (in_flight and extra_episode == 1 and covered == episodes[-1]["dataset_to_index"]),
          f"stats.json counts {covered} frames, info.json {total}")
    n_covered = sum(1 for e in episodes if e["dataset_to_index"] <= covered)
    per_episode_stats = per_episode_stats[:n_covered]
    committed = pa.concat_tables([pq.read_table(p) for p in data_paths])
    committed = committed.filter(pa.compute.less(committed.column("index"), covered))
    for k, spec in features.items():
        check(list(stats[k]) == STATS, f"stats.json {k}: keys {list(stats[k])}")
        x = column_array(committed, k, spec).reshape(covered, -1)
        want = stats_of(x)
        for s in ["min", "max", "mean", "std", "count"]:
            close(np.array(stats[k][s], dtype=np.float64), want[s], f"stats.json {k}/{s}")
        counts = np.array([e[k]["count"][0] for e in per_episode_stats], dtype=np.float64)
        for s in QUANTILES:
            weighted = sum(e[k][s] * c for e, c in zip(per_episode_stats, counts)) / counts.sum()
            close(np.array(stats[k][s], dtype=np.float64), weighted, f"stats.json {k}/{s}")

    # LeRobot's own loading path when Hugging Face `datasets` is installed (optional):
    # load_nested_dataset casts every data file to the features of info.json.
    hf_loaded = None
    try:
        import datasets as hf
    except ImportError:
        hf = None
    if hf is not None and not in_flight:
        hf_features = hf.Features({
            k: hf.Value(dtype=ft["dtype"]) if ft["shape"] == [1]
            else hf.Sequence(length=ft["shape"][0], feature=hf.Value(dtype=ft["dtype"]))
            for k, ft in features.items()
        })
        loaded = hf.concatenate_datasets([hf.Dataset.from_parquet(str(p), features=hf_features) for p in data_paths])
        check(len(loaded) == total, f"datasets loaded {len(loaded)} frames, info says {total}")
        first = loaded[0]
        check(len(first["observation.state"]) == features["observation.state"]["shape"][0], "datasets: state width")
        hf_loaded = len(loaded)

    # No NaN or infinity anywhere: LeRobot has no masking, one NaN spreads through the stats and
    # every action chunk. A joint not read in a frame period is held and marked in the mask.
    for k, x in cols.items():
        check(np.isfinite(x).all(), f"{k} has non-finite values")
    valid = cols["observation.joint_valid"]
    check(np.isin(valid, [0.0, 1.0]).all(), "observation.joint_valid is not 0/1")
    camera_valid = cols.get("observation.camera_valid")
    if camera_valid is not None:
        # One camera's mask reads as a flat column: a row per frame, a column per camera.
        camera_valid = np.asarray(camera_valid).reshape(len(camera_valid), -1)
    if videos:
        check(camera_valid is not None, "videos without observation.camera_valid")
        check(features["observation.camera_valid"]["names"] == [k.removeprefix("observation.images.") for k in videos],
              "observation.camera_valid does not name the cameras in feature order")
        check(np.isin(camera_valid, [0.0, 1.0]).all(), "observation.camera_valid is not 0/1")
    state = cols["observation.state"][:total] if orphan_rows else cols["observation.state"]
    valid = valid[:total] if orphan_rows else valid
    print(json.dumps({
        "episodes": info["total_episodes"],
        "frames": total,
        "lengths": [e["length"] for e in episodes],
        "joints": features["observation.state"]["names"],
        "grippers": features.get("observation.grip_force", {}).get("names", []),
        "data_files": [str(p.relative_to(root)) for p in data_paths],
        "orphan_rows": int(orphan_rows),
        "missing_fraction": float((valid < 0.5).mean()) if valid.size else 0.0,
        "state_span_rad": float(state.max() - state.min()) if state.size else 0.0,
        "tasks": list(tasks.index),
        "hf_datasets_loaded": hf_loaded,
        "cameras": list(videos),
        "held_images_per_camera": (camera_valid[:total] < 0.5).sum(axis=0).tolist() if videos else [],
        "held_frames_by_episode": [
            int((camera_valid[e["dataset_from_index"]:e["dataset_to_index"]] < 0.5).any(axis=1).sum())
            for e in episodes[:info["total_episodes"]]] if videos else [],
    }))


if __name__ == "__main__":
    main()
