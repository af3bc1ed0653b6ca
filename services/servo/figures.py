"""Plots of servo runs, like Sensors 2022's figures, as PNG files (matplotlib, headless).

One run (:func:`servo_plots`, from its trajectory log): the features' trajectories in the image (each point's
start and end in its own colour, the goal, the image's border), the error (its norm and each component), the
commanded velocities against the robot's limits, the joints against their limits and the manipulability. Every
time series is plotted against the arm's time, with the iteration on the top axis. Several runs
(:func:`comparison_plots`): their error norms side by side, by iteration and by time, and for an experiment the
figures it names.
"""
from __future__ import annotations

from pathlib import Path
from typing import Iterable, Optional

import numpy as np

from services.model.arm import ArmDescription
from services.servo.result import error_rms

POINT_COLOURS = ("tab:blue", "tab:orange", "tab:green", "tab:purple")


def pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def as_dicts(records: Iterable) -> list[dict]:
    return [r if isinstance(r, dict) else dict(r.__dict__) for r in records]


def times(records: list[dict], origin_ns: Optional[int] = None) -> np.ndarray:
    """The records' arm time (s) from ``origin_ns`` (default: the first record's stamp)."""
    stamps = np.array([r["stamp_ns"] for r in records], dtype=float)
    if not len(stamps):
        return stamps
    return (stamps - (stamps[0] if origin_ns is None else origin_ns)) * 1e-9


def iteration_axis(ax, times: np.ndarray, iterations: np.ndarray) -> None:
    """The iteration on the top axis of a plot against time (interpolated: frames are not evenly answered in
    realtime)."""
    keep = np.concatenate([[True], np.diff(iterations) > 0]) if len(iterations) else iterations.astype(bool)
    t, i = times[keep], iterations[keep].astype(float)
    if len(t) < 2 or np.any(np.diff(t) <= 0):
        return
    top = ax.secondary_xaxis("top", functions=(lambda x: np.interp(x, t, i), lambda k: np.interp(k, i, t)))
    top.set_xlabel("iteration", fontsize=8)
    top.tick_params(labelsize=7)


def save(fig, path: Path, paths: list) -> None:
    fig.tight_layout()
    # tight_layout leaves a placeholder layout engine behind, and savefig draws a figure that has one twice (a dry
    # run for the layout, then the pixels): without it, once (the same bytes, a fifth less time)
    fig.set_layout_engine(None)
    fig.savefig(path, dpi=110)
    pyplot().close(fig)
    paths.append(path)


def image_border(camera) -> Optional[np.ndarray]:
    """The image's corners in normalized coordinates, closed (5×2), from robot_sim's camera config."""
    if camera is None:
        return None
    cx, cy = camera.principal_point
    xs = np.array([0.0, camera.width - 1.0]) - cx
    ys = np.array([0.0, camera.height - 1.0]) - cy
    x0, x1 = xs / camera.fx
    y0, y1 = ys / camera.fy
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1], [x0, y0]])


def record_ids(record: dict) -> list:
    """The ids of an iteration's points, in their order: a keypoint target's as logged, a tag's corners 0-3."""
    keypoints = record.get("keypoints")
    return list(keypoints["ids"]) if keypoints else list(range(len(record["points"])))


def with_points(records: list[dict]) -> list[dict]:
    """The iterations at which the target was measured (any number of points)."""
    return [r for r in records if len(r["points"]) > 0]


def point_tracks(records: list[dict]) -> dict[int, np.ndarray]:
    """Each point's image trajectory by id (k×2, the iterations at which it was measured), ids in first-seen order."""
    tracks: dict[int, list] = {}
    for r in records:
        for i, p in zip(record_ids(r), r["points"]):
            tracks.setdefault(int(i), []).append(p)
    return {i: np.asarray(track, dtype=float) for i, track in tracks.items()}


#: more points than this are drawn as thin grey tracks, without a legend entry each (a keypoint target's)
MAX_NAMED_POINTS = 8


def features_plot(ax, records: list[dict], goal: Optional[np.ndarray], camera=None, title: str = "") -> None:
    border = image_border(camera)
    if border is not None:
        ax.plot(border[:, 0], border[:, 1], "-", color="0.4", lw=1.0, label="image border")
    tracks = point_tracks(with_points(records))
    few = len(tracks) <= MAX_NAMED_POINTS
    for k, (i, track) in enumerate(tracks.items()):
        colour = POINT_COLOURS[k % len(POINT_COLOURS)] if few else "0.45"
        ax.plot(track[:, 0], track[:, 1], "-", lw=1.2 if few else 0.5, color=colour,
                label=f"point {i}" if few else None)
        ax.plot(track[0, 0], track[0, 1], "o", color=colour, ms=6 if few else 2, zorder=4)
        ax.plot(track[-1, 0], track[-1, 1], "s", mfc="none", mec=colour, ms=10 if few else 3, mew=1.6 if few else 0.6,
                zorder=5)
    if tracks:
        if not few:
            ax.plot([], [], "-", color="0.45", lw=0.8, label=f"{len(tracks)} points")
        ax.plot([], [], "o", color="0.3", ms=6, label="start")
        ax.plot([], [], "s", mfc="none", mec="0.3", ms=9, mew=1.6, label="end")
    if goal is not None:
        ax.plot(goal[:, 0], goal[:, 1], "x", color="tab:red", ms=8, mew=2, zorder=6, label="goal")
    ax.set_xlabel("x (normalized)")
    ax.set_ylabel("y (normalized)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.invert_yaxis()
    ax.set_title(title or "feature trajectories", fontsize=10)
    ax.legend(fontsize=7, loc="best")
    ax.grid(alpha=0.3)


def servo_plots(records, out_dir: Path, *, law: str, arm: ArmDescription, goal=None, camera=None,
                threshold: float = 2.5e-5, robot_limits: Optional[dict] = None) -> list[Path]:
    """The figures of one run on ``arm``, written to ``out_dir``; none when the target was never seen (nothing to
    plot). ``threshold``: the convergence threshold on the per-point RMS error."""
    plt = pyplot()
    records = as_dicts(records)
    out_dir = Path(out_dir)
    paths: list[Path] = []
    seen = with_points(records)
    if not seen:
        return paths
    goal = None if goal is None else np.asarray(goal, dtype=float)

    fig, ax = plt.subplots(figsize=(6.0, 5.0))
    features_plot(ax, records, goal, camera, f"{law}: feature trajectories")
    save(fig, out_dir / "features.png", paths)

    t, it = times(seen), np.array([r["iteration"] for r in seen])
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(6.0, 6.0), sharex=True)
    top.semilogy(t, [max(error_rms(r), 1e-9) for r in seen], "-", lw=1.4, label="per-point RMS")
    top.axhline(threshold, color="tab:red", ls="--", lw=1, label=f"threshold {threshold:g}")
    top.set_ylabel("error, RMS per point")
    top.grid(alpha=0.3, which="both")
    top.legend(fontsize=8)
    iteration_axis(top, t, it)
    if max(len(r["points"]) for r in seen) <= MAX_NAMED_POINTS // 2:  # each component of a tag's error
        n = len(seen[0]["points"])
        errors = np.array([r["error"] for r in seen if len(r["error"]) == 2 * n])
        if len(errors) == len(seen):
            for k in range(2 * n):
                bottom.plot(t, errors[:, k], lw=1.0, color=POINT_COLOURS[k // 2], ls="-" if k % 2 == 0 else "--",
                            label=f"e{'xy'[k % 2]}{k // 2}")
        bottom.legend(fontsize=7, ncol=4)
    else:  # many points: the largest point's error and the number of points
        largest = [float(np.max(np.linalg.norm(np.reshape(r["error"], (-1, 2)), axis=1))) for r in seen]
        bottom.plot(t, largest, lw=1.0, color="tab:purple", label="largest point's ‖eᵢ‖")
        count = bottom.twinx()
        count.plot(t, [len(r["points"]) for r in seen], lw=0.8, color="0.5", label="points")
        count.set_ylabel("points")
        bottom.legend(fontsize=7, loc="upper right")
    bottom.set_xlabel("time (s)")
    bottom.set_ylabel("error (normalized)")
    bottom.grid(alpha=0.3)
    top.set_title(f"{law}: feature error", fontsize=10)
    save(fig, out_dir / "error.png", paths)

    commands = [r for r in seen if r["command"]]
    if commands:
        tc = times(commands, seen[0]["stamp_ns"])
        values = np.array([r["command"] for r in commands])
        fig, (first, second) = plt.subplots(2, 1, figsize=(6.0, 6.0), sharex=True)
        if commands[0].get("command_kind") == "joint_velocity":
            for k in range(values.shape[1]):
                first.plot(tc, np.degrees(values[:, k]), lw=1.0, label=f"q̇{k + 1}")
            limits = np.degrees(robot_limits["joint_speed_rps"]) if robot_limits else arm.max_speed_dps
            for value in sorted(set(np.round(limits, 6))):
                first.axhline(value, color="tab:red", ls="--", lw=0.8)
                first.axhline(-value, color="tab:red", ls="--", lw=0.8)
            first.set_ylabel("deg/s")
            first.set_title(f"{law}: commanded joint velocities (dashed: the joints' limits)", fontsize=10)
            second.plot(t, [r["ee_speed_mps"] for r in seen], lw=1.2, label="end effector, measured")
            if robot_limits:
                second.axhline(robot_limits["linear_speed_mps"], color="tab:red", ls="--", lw=0.8, label="limit")
            second.set_ylabel("m/s")
        else:
            for k, name in enumerate(("vx", "vy", "vz")):
                first.plot(tc, values[:, k], lw=1.1, label=f"{name} (base)")
            for k, name in enumerate(("ṙ", "ṗ", "ẏ")):
                second.plot(tc, values[:, 3 + k], lw=1.1, label=f"{name} (end effector)")
            if robot_limits:
                for ax, limit, unit in ((first, robot_limits["linear_speed_mps"], "m/s"),
                                        (second, robot_limits["angular_speed_rps"], "rad/s")):
                    ax.axhline(limit, color="tab:red", ls="--", lw=0.8, label=f"limit {limit:g} {unit}")
                    ax.axhline(-limit, color="tab:red", ls="--", lw=0.8)
            first.set_ylabel("m/s")
            second.set_ylabel("rad/s (rates)")
            first.set_title(f"{law}: mixed-frame velocity command", fontsize=10)
        for ax in (first, second):
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7, ncol=4)
        iteration_axis(first, t, it)
        second.set_xlabel("time (s)")
        save(fig, out_dir / "velocities.png", paths)

    with_q = [r for r in seen if len(r["q"]) == arm.n_joints]
    if with_q:
        tq = times(with_q, seen[0]["stamp_ns"])
        q_deg = np.array([arm.model_to_physical_deg(r["q"]) for r in with_q])
        limited = [i for i, j in enumerate(arm.joints) if not j.continuous]
        fig, axes = plt.subplots(len(limited) + 2, 1, figsize=(6.0, 8.5), sharex=True)
        for ax, i in zip(axes, limited):
            joint = arm.joints[i]
            ax.plot(tq, q_deg[:, i], lw=1.2, label=f"joint {i + 1}")
            for bound in (joint.lower_deg, joint.upper_deg):
                ax.axhline(bound, color="tab:red", ls="--", lw=0.8)
            span = joint.upper_deg - joint.lower_deg
            ax.set_ylim(joint.lower_deg - 0.05 * span, joint.upper_deg + 0.05 * span)
            ax.set_ylabel("deg")
            ax.legend(fontsize=7, loc="upper right")
            ax.grid(alpha=0.3)
        continuous = axes[len(limited)]
        for i, joint in enumerate(arm.joints):
            if joint.continuous:
                continuous.plot(tq, q_deg[:, i], lw=1.0, label=f"joint {i + 1}")
        continuous.set_ylabel("deg")
        continuous.legend(fontsize=7, ncol=4, title="continuous joints", title_fontsize=7)
        continuous.grid(alpha=0.3)
        axes[-1].plot(t, [r["manipulability"] for r in seen], lw=1.2, color="tab:brown")
        axes[-1].set_ylabel("manipulability")
        axes[-1].set_xlabel("time (s)")
        axes[-1].grid(alpha=0.3)
        axes[0].set_title(f"{law}: joints against their limits (dashed), manipulability", fontsize=10)
        iteration_axis(axes[0], t, it)
        save(fig, out_dir / "joints.png", paths)
    return paths


def comparison_plots(runs: dict[str, list], out_dir: Path, *, title: str, threshold: float = 2.5e-5,
                     zone_distance: bool = False, goal=None, camera=None) -> list[Path]:
    """Figures comparing runs (label → trajectory records): the per-point RMS errors by iteration and by time
    (``threshold``: the convergence threshold on it), each run's features side by side, and with ``zone_distance``
    the end effector's distance to the protection zone."""
    plt = pyplot()
    out_dir = Path(out_dir)
    paths: list[Path] = []
    runs = {label: with_points(as_dicts(records)) for label, records in runs.items()}
    runs = {label: records for label, records in runs.items() if records}
    if not runs:
        return paths
    fig, (by_iteration, by_time) = plt.subplots(1, 2, figsize=(11.0, 4.2), sharey=True)
    for label, records in runs.items():
        norms = [max(error_rms(r), 1e-9) for r in records]
        by_iteration.semilogy([r["iteration"] for r in records], norms, lw=1.4, label=label)
        by_time.semilogy(times(records), norms, lw=1.4, label=label)
    for ax, xlabel in ((by_iteration, "iteration"), (by_time, "time (s)")):
        ax.axhline(threshold, color="tab:red", ls="--", lw=1)
        ax.set_xlabel(xlabel)
        ax.grid(alpha=0.3, which="both")
    by_iteration.set_ylabel("error, RMS per point")
    by_iteration.legend(fontsize=8)
    by_iteration.set_title(f"{title}: feature error", fontsize=10)
    save(fig, out_dir / "errors.png", paths)

    fig, axes = plt.subplots(1, len(runs), figsize=(4.6 * len(runs), 4.4), squeeze=False)
    goal = None if goal is None else np.asarray(goal, dtype=float)
    for ax, (label, records) in zip(axes[0], runs.items()):
        features_plot(ax, records, goal, camera, label)
    save(fig, out_dir / "features.png", paths)

    if zone_distance:
        fig, ax = plt.subplots(figsize=(6.0, 3.8))
        for label, records in runs.items():
            distances = [r.get("zone_distance_m") for r in records]
            if all(d is not None for d in distances):
                ax.plot(times(records), distances, lw=1.4, label=label)
        ax.axhline(0.0, color="tab:red", ls="--", lw=1, label="zone boundary")
        ax.set_xlabel("time (s)")
        ax.set_ylabel("distance to the zone (m)")
        ax.set_title("end effector to the nearest protection zone", fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        save(fig, out_dir / "zone_distance.png", paths)
    return paths


