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

_POINT_COLOURS = ("tab:blue", "tab:orange", "tab:green", "tab:purple")


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _as_dicts(records: Iterable) -> list[dict]:
    return [r if isinstance(r, dict) else dict(r.__dict__) for r in records]


def _times(records: list[dict], origin_ns: Optional[int] = None) -> np.ndarray:
    """The records' arm time (s) from ``origin_ns`` (default: the first record's stamp)."""
    stamps = np.array([r["stamp_ns"] for r in records], dtype=float)
    if not len(stamps):
        return stamps
    return (stamps - (stamps[0] if origin_ns is None else origin_ns)) * 1e-9


def _iteration_axis(ax, times: np.ndarray, iterations: np.ndarray) -> None:
    """The iteration on the top axis of a plot against time (interpolated: frames are not evenly answered in
    realtime)."""
    keep = np.concatenate([[True], np.diff(iterations) > 0]) if len(iterations) else iterations.astype(bool)
    t, i = times[keep], iterations[keep].astype(float)
    if len(t) < 2 or np.any(np.diff(t) <= 0):
        return
    top = ax.secondary_xaxis("top", functions=(lambda x: np.interp(x, t, i), lambda k: np.interp(k, i, t)))
    top.set_xlabel("iteration", fontsize=8)
    top.tick_params(labelsize=7)


def _save(fig, path: Path, paths: list) -> None:
    fig.tight_layout()
    # tight_layout leaves a placeholder layout engine behind, and savefig draws a figure that has one twice (a dry
    # run for the layout, then the pixels): without it, once (the same bytes, a fifth less time)
    fig.set_layout_engine(None)
    fig.savefig(path, dpi=110)
    _pyplot().close(fig)
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


def features_plot(ax, records: list[dict], goal: Optional[np.ndarray], camera=None, title: str = "") -> None:
    with_points = [r for r in records if len(r["points"]) == 4]
    border = image_border(camera)
    if border is not None:
        ax.plot(border[:, 0], border[:, 1], "-", color="0.4", lw=1.0, label="image border")
    if with_points:
        pts = np.array([r["points"] for r in with_points])
        for i in range(4):
            colour = _POINT_COLOURS[i]
            ax.plot(pts[:, i, 0], pts[:, i, 1], "-", lw=1.2, color=colour, label=f"point {i}")
            ax.plot(pts[0, i, 0], pts[0, i, 1], "o", color=colour, ms=6, zorder=4)
            ax.plot(pts[-1, i, 0], pts[-1, i, 1], "s", mfc="none", mec=colour, ms=10, mew=1.6, zorder=5)
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
                threshold: float = 5e-5, robot_limits: Optional[dict] = None) -> list[Path]:
    """The figures of one run on ``arm``, written to ``out_dir``; none when the tag was never seen (nothing to
    plot)."""
    plt = _pyplot()
    records = _as_dicts(records)
    out_dir = Path(out_dir)
    paths: list[Path] = []
    seen = [r for r in records if len(r["points"]) == 4]
    if not seen:
        return paths
    goal = None if goal is None else np.asarray(goal, dtype=float)

    fig, ax = plt.subplots(figsize=(6.0, 5.0))
    features_plot(ax, records, goal, camera, f"{law}: feature trajectories")
    _save(fig, out_dir / "features.png", paths)

    t, it = _times(seen), np.array([r["iteration"] for r in seen])
    errors = np.array([r["error"] for r in seen if len(r["error"]) == 8])
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(6.0, 6.0), sharex=True)
    top.semilogy(t, [max(r["error_norm"], 1e-9) for r in seen], "-", lw=1.4, label="‖e‖")
    top.axhline(threshold, color="tab:red", ls="--", lw=1, label=f"threshold {threshold:g}")
    top.set_ylabel("‖e‖")
    top.grid(alpha=0.3, which="both")
    top.legend(fontsize=8)
    _iteration_axis(top, t, it)
    if len(errors) == len(seen):
        for k in range(8):
            bottom.plot(t, errors[:, k], lw=1.0, color=_POINT_COLOURS[k // 2], ls="-" if k % 2 == 0 else "--",
                        label=f"e{'xy'[k % 2]}{k // 2}")
    bottom.set_xlabel("time (s)")
    bottom.set_ylabel("error (normalized)")
    bottom.grid(alpha=0.3)
    bottom.legend(fontsize=7, ncol=4)
    top.set_title(f"{law}: feature error", fontsize=10)
    _save(fig, out_dir / "error.png", paths)

    commands = [r for r in seen if r["command"]]
    if commands:
        tc = _times(commands, seen[0]["stamp_ns"])
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
        _iteration_axis(first, t, it)
        second.set_xlabel("time (s)")
        _save(fig, out_dir / "velocities.png", paths)

    with_q = [r for r in seen if len(r["q"]) == arm.n_joints]
    if with_q:
        tq = _times(with_q, seen[0]["stamp_ns"])
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
        _iteration_axis(axes[0], t, it)
        _save(fig, out_dir / "joints.png", paths)
    return paths


def comparison_plots(runs: dict[str, list], out_dir: Path, *, title: str, threshold: float = 5e-5,
                     zone_distance: bool = False, goal=None, camera=None) -> list[Path]:
    """Figures comparing runs (label → trajectory records): the error norms by iteration and by time, each
    run's features side by side, and with ``zone_distance`` the end effector's distance to the protection zone."""
    plt = _pyplot()
    out_dir = Path(out_dir)
    paths: list[Path] = []
    runs = {label: [r for r in _as_dicts(records) if len(r["points"]) == 4] for label, records in runs.items()}
    runs = {label: records for label, records in runs.items() if records}
    if not runs:
        return paths
    fig, (by_iteration, by_time) = plt.subplots(1, 2, figsize=(11.0, 4.2), sharey=True)
    for label, records in runs.items():
        norms = [max(r["error_norm"], 1e-9) for r in records]
        by_iteration.semilogy([r["iteration"] for r in records], norms, lw=1.4, label=label)
        by_time.semilogy(_times(records), norms, lw=1.4, label=label)
    for ax, xlabel in ((by_iteration, "iteration"), (by_time, "time (s)")):
        ax.axhline(threshold, color="tab:red", ls="--", lw=1)
        ax.set_xlabel(xlabel)
        ax.grid(alpha=0.3, which="both")
    by_iteration.set_ylabel("‖e‖")
    by_iteration.legend(fontsize=8)
    by_iteration.set_title(f"{title}: feature error", fontsize=10)
    _save(fig, out_dir / "errors.png", paths)

    fig, axes = plt.subplots(1, len(runs), figsize=(4.6 * len(runs), 4.4), squeeze=False)
    goal = None if goal is None else np.asarray(goal, dtype=float)
    for ax, (label, records) in zip(axes[0], runs.items()):
        features_plot(ax, records, goal, camera, label)
    _save(fig, out_dir / "features.png", paths)

    if zone_distance:
        fig, ax = plt.subplots(figsize=(6.0, 3.8))
        for label, records in runs.items():
            distances = [r.get("zone_distance_m") for r in records]
            if all(d is not None for d in distances):
                ax.plot(_times(records), distances, lw=1.4, label=label)
        ax.axhline(0.0, color="tab:red", ls="--", lw=1, label="zone boundary")
        ax.set_xlabel("time (s)")
        ax.set_ylabel("distance to the zone (m)")
        ax.set_title("end effector to the nearest protection zone", fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        _save(fig, out_dir / "zone_distance.png", paths)
    return paths


# ------------------------------------------------------------------------------------------------ Muñoz 2018
def _limits_y(ax, values: np.ndarray, band: float) -> None:
    """φ can sit far below 0 while inactive: show the neighbourhood of the band, not the whole range."""
    finite = values[np.isfinite(values)]
    if not len(finite):
        return
    reach = max(20.0 * band, 0.5 * float(np.ptp(finite[finite > -1e3])) if np.any(finite > -1e3) else 1.0, 1e-6)
    ax.set_ylim(max(float(finite.min()), -reach), max(float(finite.max()), 2.0 * band) + 0.1 * reach)


def constraint_plots(runs: dict[str, list], out_dir: Path, *, law_options: dict, camera=None, goal=None) -> list[Path]:
    """Seed 002's figures for runs of the sliding-mode law (label → trajectory records): each constraint type's
    largest φ over time against its chattering band T_s·u⁺ with the time it was active marked (like the paper's
    Fig. 11), and the features in the image with the field of view's hyperellipse and the occlusion regions."""
    plt = _pyplot()
    out_dir = Path(out_dir)
    paths: list[Path] = []
    runs = {label: [r for r in _as_dicts(records) if r.get("notes")] for label, records in runs.items()}
    kinds = sorted({k.split(".", 1)[1] for records in runs.values() for r in records for k in r["notes"]
                    if k.startswith("max_phi.")})
    if not kinds:
        return paths
    fig, axes = plt.subplots(len(kinds), 1, figsize=(9.0, 2.3 * len(kinds)), sharex=True, squeeze=False)
    for ax, kind in zip(axes[:, 0], kinds):
        every = []
        for index, (label, records) in enumerate(runs.items()):
            steps = [r for r in records if f"max_phi.{kind}" in r["notes"]]
            if not steps:
                continue
            t = _times(steps, records[0]["stamp_ns"])
            phi = np.array([r["notes"][f"max_phi.{kind}"] for r in steps])
            band = np.array([r["notes"][f"band.{kind}"] for r in steps])
            active = np.array([r["notes"].get(f"active.{kind}", 0) > 0 for r in steps])
            colour = f"C{index}"
            ax.plot(t, phi, lw=1.2, color=colour, label=f"{label}: max φ")
            ax.plot(t, band, ls="--", lw=1.0, color=colour, alpha=0.7, label=f"{label}: band T_s·u⁺")
            ax.plot(t[active], phi[active], "|", color=colour, ms=7, label=f"{label}: active")
            every.extend([*phi, *band])
        ax.axhline(0.0, color="0.3", lw=0.8)
        _limits_y(ax, np.array(every), float(np.median(every)) if every else 0.0)
        ax.set_ylabel(f"φ {kind}")
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=7, ncol=3, loc="lower right")
    axes[0, 0].set_title("constraint functions against their chattering bands (eq. 43)", fontsize=10)
    axes[-1, 0].set_xlabel("time (s)")
    _save(fig, out_dir / "constraints.png", paths)

    fig, axes = plt.subplots(1, len(runs), figsize=(5.0 * len(runs), 4.4), squeeze=False)
    goal = None if goal is None else np.asarray(goal, dtype=float)
    for ax, (label, records) in zip(axes[0], runs.items()):
        features_plot(ax, records, goal, camera, label)
        _constraint_regions(ax, law_options, camera)
    _save(fig, out_dir / "constraint_image.png", paths)
    return paths


def _constraint_regions(ax, law_options: dict, camera) -> None:
    """The field of view's hyperellipse and the occlusion regions, as the sliding-mode law sees them."""
    from services.controller.smc import SmcOptions

    options = SmcOptions.from_dict({k: v for k, v in law_options.items() if k in ("fov", "occlusions")})
    angle = np.linspace(0.0, 2.0 * np.pi, 400)

    def superellipse(centre, semi_axes, n):
        c, s = np.cos(angle), np.sin(angle)
        return (centre[0] + semi_axes[0] * np.sign(c) * np.abs(c) ** (2.0 / n),
                centre[1] + semi_axes[1] * np.sign(s) * np.abs(s) ** (2.0 / n))

    if options.fov is not None:
        fov = options.fov
        if camera is not None:
            fov.width, fov.height, fov.fx, fov.fy = camera.width, camera.height, camera.fx, camera.fy
        ax.plot(*superellipse((0.0, 0.0), fov.semi_axes, fov.exponent), ":", color="tab:red", lw=1.0,
                label="field of view (margin)")
    for k, occlusion in enumerate(options.occlusions):
        x, y = superellipse(occlusion.centre, occlusion.semi_axes, occlusion.exponent)
        ax.fill(x, y, color="0.5", alpha=0.35, label="occlusion" if k == 0 else None)
    ax.legend(fontsize=7, loc="best")


# ------------------------------------------------------------------------------------------------ Nelson 1995
def tracking_plots(runs: dict[str, list], out_dir: Path, *, target_start, target_velocity,
                   failures: dict, arm: ArmDescription) -> list[Path]:
    """Seed 004's figures (label → trajectory records): the modified manipulability w'(q) and Yoshikawa's w over
    time, the joints' margin to their limits, and a top view of the target's path (from ``target_start`` at the
    arm's time 0, at ``target_velocity``, base frame) and the end effector's."""
    from services.model.kinematics import ArmKinematics

    plt = _pyplot()
    out_dir = Path(out_dir)
    paths: list[Path] = []
    runs = {label: _as_dicts(records) for label, records in runs.items() if records}
    if not runs:
        return paths
    fig, (w_ax, margin_ax) = plt.subplots(2, 1, figsize=(9.0, 6.0), sharex=True)
    for index, (label, records) in enumerate(runs.items()):
        colour = f"C{index}"
        t = _times(records, 0)
        w_prime = np.array([r["notes"].get("w_prime", np.nan) for r in records])
        w = np.array([r["manipulability"] for r in records])
        w_ax.semilogy(t, np.maximum(w_prime, 1e-12), color=colour, lw=1.3, label=f"{label}: w'(q)")
        w_ax.semilogy(t, np.maximum(w, 1e-12) ** 2, color=colour, lw=1.0, ls="--", label=f"{label}: w² (Yoshikawa)")
        margin = arm.limit_margins_deg(np.array([r["q"] for r in records])).min(axis=1)
        margin_ax.plot(t, margin, color=colour, lw=1.3, label=f"{label} ({failures.get(label) or 'path end'})")
    w_ax.set_ylabel("manipulability")
    w_ax.legend(fontsize=7, ncol=2)
    w_ax.grid(alpha=0.3, which="both")
    w_ax.set_title("configuration while tracking", fontsize=10)
    margin_ax.axhline(0.0, color="tab:red", ls="--", lw=1)
    margin_ax.set_ylabel("nearest joint limit (deg)")
    margin_ax.set_xlabel("time (s)")
    margin_ax.legend(fontsize=7)
    margin_ax.grid(alpha=0.3)
    _save(fig, out_dir / "manipulability.png", paths)

    kin = ArmKinematics(arm)
    start = np.asarray(target_start, dtype=float)
    velocity = np.asarray(target_velocity, dtype=float)
    fig, ax = plt.subplots(figsize=(6.4, 6.0))
    end_s = max(_times(records, 0)[-1] for records in runs.values())
    target = start + np.outer(np.linspace(0.0, end_s, 50), velocity)
    ax.plot(target[:, 0], target[:, 1], "-", color="0.3", lw=2.0, label="target")
    for index, (label, records) in enumerate(runs.items()):
        ee = np.array([kin.pose(np.asarray(r["q"]))[1] for r in records])
        colour = f"C{index}"
        ax.plot(ee[:, 0], ee[:, 1], "-", color=colour, lw=1.3, label=f"{label}: end effector")
        tracked = [r for r in records if len(r["points"]) == 4]
        if tracked:
            t_end = tracked[-1]["stamp_ns"] * 1e-9
            at = start + velocity * t_end
            ax.plot(*at[:2], "X", color=colour, ms=10, label=f"{label}: last tracked ({failures.get(label) or 'path end'})")
    reach = np.linspace(0.0, 2.0 * np.pi, 200)
    ax.plot(arm.reach * np.cos(reach), arm.reach * np.sin(reach), ":", color="0.5",
            label="arm's straight reach")
    ax.plot(0.0, 0.0, "k^", ms=8, label="base")
    ax.set_xlabel("x (m, base)")
    ax.set_ylabel("y (m, base)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="best")
    ax.set_title("top view: the target's path and the end effector's", fontsize=10)
    _save(fig, out_dir / "tracking_paths.png", paths)
    return paths


def random_starts_plots(runs: list[dict], starts: list[dict], out_dir: Path, *, laws: list[str], paper: dict,
                        clearly_faster_pct: float) -> list[Path]:
    """Table 3 over random starts: each law's iterations to converge over the starts (a box per law, every start a
    dot, the paper's count a red mark; failures counted under the box), and the mixed law's improvement over
    adaptive-pd-joint start by start against the bar it should clear and the paper's."""
    plt = _pyplot()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths: list[Path] = []
    fig, (box, gain) = plt.subplots(1, 2, figsize=(12.0, 4.4), gridspec_kw={"width_ratios": [3, 2]})
    data = [[r["iterations"] for r in runs if r["law"] == law and r["converged"]] for law in laws]
    positions = np.arange(1, len(laws) + 1)
    box.boxplot([d if d else [np.nan] for d in data], positions=positions, widths=0.5, showfliers=False)
    for x, values in zip(positions, data):
        jitter = np.linspace(-0.12, 0.12, len(values)) if len(values) > 1 else np.zeros(len(values))
        box.plot(x + jitter, values, "o", ms=3, alpha=0.6, color="tab:blue")
    box.plot(positions, [paper[law] for law in laws], "_", ms=22, mew=2.5, color="tab:red", label="paper (Table 3)")
    for x, law in zip(positions, laws):
        failed = sum(1 for r in runs if r["law"] == law and not r["converged"])
        box.annotate(f"{failed} failed" if failed else "all converged", (x, 0), xycoords=("data", "axes fraction"),
                     xytext=(0, 4), textcoords="offset points", ha="center", fontsize=7)
    box.set_xticks(positions, laws, fontsize=8)
    box.set_ylabel("iterations to ‖e‖ < 5e-5")
    box.set_title(f"iterations over {len(starts)} random starts", fontsize=10)
    box.legend(fontsize=8)
    box.grid(alpha=0.3, axis="y")
    values = [s["improvement_pct"] for s in starts]
    colours = ["tab:green" if s["clearly_faster"] else "tab:red" for s in starts]
    indices = [s["start"]["index"] for s in starts]
    gain.bar(range(len(starts)), [v if v is not None else 0.0 for v in values], color=colours)
    for i, v in enumerate(values):
        if v is None:
            gain.annotate("failed", (i, 0), ha="center", va="bottom", fontsize=7, rotation=90)
    gain.axhline(clearly_faster_pct, color="tab:gray", ls="--", lw=1, label=f"{clearly_faster_pct:g} %")
    paper_pct = 100.0 * (paper["adaptive-pd-joint"] - paper["adaptive-pd-mixed"]) / paper["adaptive-pd-joint"]
    gain.axhline(paper_pct, color="tab:red", ls=":", lw=1, label=f"paper {paper_pct:.1f} %")
    gain.set_xticks(range(len(starts)), indices, fontsize=7)
    gain.set_xlabel("start")
    gain.set_ylabel("mixed law: fewer iterations than joint PD (%)")
    gain.set_title("the mixed law's improvement, start by start", fontsize=10)
    gain.legend(fontsize=8)
    gain.grid(alpha=0.3, axis="y")
    _save(fig, out_dir / "random_starts.png", paths)
    return paths


# ------------------------------------------------------------------------------------------------ JACO thesis
_POSE_NAMES = ("x (m)", "y (m)", "z (m)", "α (rad)", "β (rad)", "γ (rad)")


def _unwrapped_pose(x: np.ndarray) -> np.ndarray:
    """[p; XYZ Euler] samples with the angles unwrapped (a reported angle jumps by 2π where it crosses ±π)."""
    x = np.array(x, dtype=float, copy=True)
    if len(x):
        x[:, 3:] = np.unwrap(x[:, 3:], axis=0)
    return x


def _joint_grid(plt, n: int):
    """A figure with a panel per joint, two to a row (a spare panel hidden), and its panels in joint order."""
    rows = (n + 1) // 2
    fig, axes = plt.subplots(rows, 2, figsize=(10.0, 2.0 * rows + 0.8), sharex=True, squeeze=False)
    for ax in axes.flat[n:]:
        ax.axis("off")
    for ax in axes[-1]:
        ax.set_xlabel("time (s)")
    return fig, list(axes.flat[:n])


def torque_run_plots(arrays: dict, meta: dict, out_dir: Path, *, arm: ArmDescription, label: str) -> list[Path]:
    """One torque-control run's figures (JACO thesis Figs. 5.1-5.5): a task run's position and XYZ Euler angles
    against the reference, a joint run's joints against the sinusoid; and every run's torques against the joints'
    limits (commanded: what the controller asked, gravity included)."""
    plt = _pyplot()
    out_dir = Path(out_dir)
    paths: list[Path] = []
    t = arrays["t"]
    if not len(t):
        return paths
    tf = meta.get("reference_s")
    if np.isfinite(arrays["x_d"]).all():
        x, x_d = _unwrapped_pose(arrays["x"]), _unwrapped_pose(arrays["x_d"])
        x_d[:, 3:] += np.round((x[:1, 3:] - x_d[:1, 3:]) / (2 * np.pi)) * 2 * np.pi  # the same turn as measured
        fig, axes = plt.subplots(2, 3, figsize=(12.0, 6.2), sharex=True)
        for k, ax in enumerate(axes.flat):
            ax.plot(t, x_d[:, k], "--", color="0.35", lw=1.2, label="reference (eq. 5.1)")
            ax.plot(t, x[:, k], lw=1.3, color="tab:blue", label="measured")
            ax.set_ylabel(_POSE_NAMES[k])
            ax.grid(alpha=0.3)
            if tf:
                ax.axvline(tf, color="tab:gray", ls=":", lw=0.8)
        for ax in axes[1]:
            ax.set_xlabel("time (s)")
        axes[0][0].legend(fontsize=8)
        fig.suptitle(f"{label} on the {arm.name}: position and XYZ Euler angles against the reference", fontsize=10)
        _save(fig, out_dir / "pose.png", paths)

        fig, (top, bottom) = plt.subplots(2, 1, figsize=(7.0, 5.2), sharex=True)
        top.plot(t, arrays["position_error_m"] * 1e3, lw=1.2)
        top.set_ylabel("position error (mm)")
        bottom.plot(t, arrays["orientation_error_deg"], lw=1.2, color="tab:orange")
        bottom.set_ylabel("orientation error (deg)")
        bottom.set_xlabel("time (s)")
        for ax in (top, bottom):
            ax.grid(alpha=0.3)
            if tf:
                ax.axvline(tf, color="tab:gray", ls=":", lw=0.8)
        top.set_title(f"{label}: tracking error", fontsize=10)
        _save(fig, out_dir / "error.png", paths)
    else:
        n = arm.n_joints
        q0 = arrays["q"][0] if meta.get("q0") is None else np.asarray(meta["q0"])
        fig, axes = _joint_grid(plt, n)
        for i, ax in enumerate(axes):
            ax.plot(t, np.degrees(arrays["q_d"][:, i] - q0[i]), "--", color="0.35", lw=1.1, label="q_d (eq. 5.3)")
            ax.plot(t, np.degrees(arrays["q"][:, i] - q0[i]), lw=1.3, label="q")
            ax.set_ylabel(f"joint {i + 1} (deg)")
            ax.grid(alpha=0.3)
        axes[0].legend(fontsize=8)
        fig.suptitle(f"{label} on the {arm.name}: each joint about its start against the sinusoid", fontsize=10)
        _save(fig, out_dir / "joints.png", paths)

    limits = np.asarray(meta["torque_limits_nm"])
    fig, axes = _joint_grid(plt, len(limits))
    for i, ax in enumerate(axes):
        ax.plot(t, arrays["tau_command"][:, i], lw=1.0, label="commanded")
        ax.plot(t, arrays["tau_measured"][:, i], lw=0.8, alpha=0.7, label="measured (the actuator's)")
        for sign in (1, -1):
            ax.axhline(sign * limits[i], color="tab:red", ls="--", lw=0.8)
        peak = max(float(np.abs(arrays["tau_command"][:, i]).max()), float(np.abs(arrays["tau_measured"][:, i]).max()))
        if peak < 0.5 * limits[i]:  # far from the limits: show the torque, not the empty band up to them
            ax.set_ylim(-1.15 * max(peak, 1e-3), 1.15 * max(peak, 1e-3))
        ax.set_ylabel(f"τ{i + 1} (N·m)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle(f"{label}: joint torques (dashed: the limits, where in range)", fontsize=10)
    _save(fig, out_dir / "torques.png", paths)

    if len(arrays.get("latency_ms", ())) == len(t):
        fig, ax = plt.subplots(figsize=(8.0, 3.4))
        ax.semilogy(t, np.maximum(arrays["latency_ms"], 1e-3), ".", ms=1.5, label="state's stamp → answer sent")
        ax.semilogy(t, np.maximum(arrays["response_ms"], 1e-3), ".", ms=1.5, label="state's arrival → answer sent")
        ax.axhline(2.0, color="tab:red", ls="--", lw=0.8, label="a bus cycle (2 ms)")
        ax.set_xlabel("time (s)")
        ax.set_ylabel("ms")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7, markerscale=6)
        ax.set_title(f"{label}: the low-level loop, answer by answer", fontsize=10)
        _save(fig, out_dir / "timing.png", paths)
    return paths


def torque_comparison_plots(runs: dict[str, dict], metas: dict[str, dict], out_dir: Path, *,
                            arm: ArmDescription) -> list[Path]:
    """The torque-control runs side by side: each task run's position and orientation error, each joint run's
    worst joint error."""
    plt = _pyplot()
    out_dir = Path(out_dir)
    paths: list[Path] = []
    task = {k: v for k, v in runs.items() if len(v["t"]) and np.isfinite(v["x_d"]).all()}
    joint = {k: v for k, v in runs.items() if len(v["t"]) and k not in task}
    if task:
        fig, (top, bottom) = plt.subplots(2, 1, figsize=(8.0, 6.4), sharex=True)
        for label, a in task.items():
            top.plot(a["t"], a["position_error_m"] * 1e3, lw=1.1, label=label)
            bottom.plot(a["t"], a["orientation_error_deg"], lw=1.1, label=label)
        top.set_yscale("log")
        top.set_ylim(bottom=1e-2)  # the first sample is at the reference: its zero would stretch the axis
        top.set_ylabel("position error (mm)")
        bottom.set_ylabel("orientation error (deg)")
        bottom.set_xlabel("time (s)")
        for ax in (top, bottom):
            ax.grid(alpha=0.3, which="both")
        top.legend(fontsize=7, ncol=2)
        top.set_title(f"task-space controllers on the {arm.name}", fontsize=10)
        _save(fig, out_dir / "task_errors.png", paths)
    if joint:
        fig, ax = plt.subplots(figsize=(8.0, 3.8))
        for label, a in joint.items():
            ax.plot(a["t"], np.degrees(np.abs(a["q_d"] - a["q"])).max(axis=1), lw=1.1, label=label)
        ax.set_ylabel("largest joint error (deg)")
        ax.set_xlabel("time (s)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
        ax.set_title(f"joint-space controllers on the {arm.name}", fontsize=10)
        _save(fig, out_dir / "joint_errors.png", paths)
    return paths
