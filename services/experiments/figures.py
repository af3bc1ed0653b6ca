"""The experiments' own figures, as PNG files (matplotlib, headless): the constraints over time, the tracked
target's path, the random starts' iterations, and the torque controllers' runs (the JACO thesis's Figs. 5.1-5.5).
A servo run's figures and the common plotting helpers are :mod:`services.servo.figures`."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from services.model.arm import ArmDescription
from services.servo.figures import as_dicts, features_plot, pyplot, save, times, with_points


# ------------------------------------------------------------------------------------------------ Muñoz 2018
def _limits_y(ax, values: np.ndarray, band: float) -> None:
    """φ can sit far below 0 while inactive: show the neighbourhood of the band, not the whole range."""
    finite = values[np.isfinite(values)]
    if not len(finite):
        return
    reach = max(20.0 * band, 0.5 * float(np.ptp(finite[finite > -1e3])) if np.any(finite > -1e3) else 1.0, 1e-6)
    ax.set_ylim(max(float(finite.min()), -reach), max(float(finite.max()), 2.0 * band) + 0.1 * reach)


def constraint_plots(runs: dict[str, list], out_dir: Path, *, law_options: dict, camera=None, goal=None) -> list[Path]:
    """Muñoz 2018's figures for runs of the sliding-mode law (label → trajectory records): each constraint type's
    largest φ over time against its chattering band T_s·u⁺ with the time it was active marked (like the paper's
    Fig. 11), and the features in the image with the field of view's hyperellipse and the occlusion regions."""
    plt = pyplot()
    out_dir = Path(out_dir)
    paths: list[Path] = []
    runs = {label: [r for r in as_dicts(records) if r.get("notes")] for label, records in runs.items()}
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
            t = times(steps, records[0]["stamp_ns"])
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
    save(fig, out_dir / "constraints.png", paths)

    fig, axes = plt.subplots(1, len(runs), figsize=(5.0 * len(runs), 4.4), squeeze=False)
    goal = None if goal is None else np.asarray(goal, dtype=float)
    for ax, (label, records) in zip(axes[0], runs.items()):
        features_plot(ax, records, goal, camera, label)
        _constraint_regions(ax, law_options, camera)
    save(fig, out_dir / "constraint_image.png", paths)
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
    """Nelson 1995's figures (label → trajectory records): the modified manipulability w'(q) and Yoshikawa's w over
    time, the joints' margin to their limits, and a top view of the target's path (from ``target_start`` at the
    arm's time 0, at ``target_velocity``, base frame) and the end effector's."""
    from services.model.kinematics import ArmKinematics

    plt = pyplot()
    out_dir = Path(out_dir)
    paths: list[Path] = []
    runs = {label: as_dicts(records) for label, records in runs.items() if records}
    if not runs:
        return paths
    fig, (w_ax, margin_ax) = plt.subplots(2, 1, figsize=(9.0, 6.0), sharex=True)
    for index, (label, records) in enumerate(runs.items()):
        colour = f"C{index}"
        t = times(records, 0)
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
    save(fig, out_dir / "manipulability.png", paths)

    kin = ArmKinematics(arm)
    start = np.asarray(target_start, dtype=float)
    velocity = np.asarray(target_velocity, dtype=float)
    fig, ax = plt.subplots(figsize=(6.4, 6.0))
    end_s = max(times(records, 0)[-1] for records in runs.values())
    target = start + np.outer(np.linspace(0.0, end_s, 50), velocity)
    ax.plot(target[:, 0], target[:, 1], "-", color="0.3", lw=2.0, label="target")
    for index, (label, records) in enumerate(runs.items()):
        ee = np.array([kin.pose(np.asarray(r["q"]))[1] for r in records])
        colour = f"C{index}"
        ax.plot(ee[:, 0], ee[:, 1], "-", color=colour, lw=1.3, label=f"{label}: end effector")
        tracked = with_points(records)
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
    save(fig, out_dir / "tracking_paths.png", paths)
    return paths


def random_starts_plots(runs: list[dict], starts: list[dict], out_dir: Path, *, laws: list[str], paper: dict,
                        clearly_faster_pct: float) -> list[Path]:
    """Table 3 over random starts: each law's iterations to converge over the starts (a box per law, every start a
    dot, the paper's count a red mark; failures counted under the box), and the mixed law's improvement over
    adaptive-pd-joint start by start against the bar it should clear and the paper's."""
    plt = pyplot()
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
    save(fig, out_dir / "random_starts.png", paths)
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
    plt = pyplot()
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
        save(fig, out_dir / "pose.png", paths)

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
        save(fig, out_dir / "error.png", paths)
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
        save(fig, out_dir / "joints.png", paths)

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
    save(fig, out_dir / "torques.png", paths)

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
        save(fig, out_dir / "timing.png", paths)
    return paths


def torque_comparison_plots(runs: dict[str, dict], metas: dict[str, dict], out_dir: Path, *,
                            arm: ArmDescription) -> list[Path]:
    """The torque-control runs side by side: each task run's position and orientation error, each joint run's
    worst joint error."""
    plt = pyplot()
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
        save(fig, out_dir / "task_errors.png", paths)
    if joint:
        fig, ax = plt.subplots(figsize=(8.0, 3.8))
        for label, a in joint.items():
            ax.plot(a["t"], np.degrees(np.abs(a["q_d"] - a["q"])).max(axis=1), lw=1.1, label=label)
        ax.set_ylabel("largest joint error (deg)")
        ax.set_xlabel("time (s)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
        ax.set_title(f"joint-space controllers on the {arm.name}", fontsize=10)
        save(fig, out_dir / "joint_errors.png", paths)
    return paths
