"""Plots of a servo run, like seed 000's Figure 9: feature trajectories in the image, error decay, and the
commanded velocities. Written as PNG files (matplotlib, headless)."""
from __future__ import annotations

from pathlib import Path

import numpy as np


def servo_plots(records, scenario, out_dir: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    paths = []
    with_points = [r for r in records if len(r.points) == 4]
    fig, ax = plt.subplots(figsize=(5.5, 4.5))
    if with_points:
        pts = np.array([r.points for r in with_points])
        for i in range(4):
            ax.plot(pts[:, i, 0], pts[:, i, 1], "-", lw=1.2, label=f"point {i}")
            ax.plot(pts[0, i, 0], pts[0, i, 1], "o", color="tab:blue", ms=5)
            ax.plot(pts[-1, i, 0], pts[-1, i, 1], "s", color="tab:green", ms=5)
    if scenario.goal.features is not None:
        goal = np.array(scenario.goal.features)
        ax.plot(goal[:, 0], goal[:, 1], "x", color="tab:red", ms=9, mew=2, label="goal")
    ax.set_xlabel("x (normalized)")
    ax.set_ylabel("y (normalized)")
    ax.invert_yaxis()
    ax.set_title(f"{scenario.law}: feature trajectories")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    paths.append(out_dir / "features.png")
    fig.tight_layout()
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    it = [r.iteration for r in records]
    ax.semilogy(it, [max(r.error_norm, 1e-9) for r in records], "-", lw=1.4)
    ax.axhline(scenario.convergence.error_norm, color="tab:red", ls="--", lw=1, label="threshold")
    ax.set_xlabel("iteration")
    ax.set_ylabel("‖e‖")
    ax.set_title("feature error")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    paths.append(out_dir / "error.png")
    fig.tight_layout()
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)

    commands = [r for r in records if r.command]
    if commands:
        fig, ax = plt.subplots(figsize=(5.5, 3.8))
        values = np.array([r.command for r in commands])
        its = [r.iteration for r in commands]
        labels = ([f"q̇{i + 1}" for i in range(7)] if values.shape[1] == 7 else
                  ["vx (base)", "vy (base)", "vz (base)", "ṙ", "ṗ", "ẏ"])
        for k in range(values.shape[1]):
            ax.plot(its, values[:, k], lw=1.1, label=labels[k])
        ax.set_xlabel("iteration")
        ax.set_ylabel("rad/s" if values.shape[1] == 7 else "m/s, rad/s")
        ax.set_title("commanded joint velocities" if values.shape[1] == 7 else "mixed-frame velocity")
        ax.legend(fontsize=7, ncol=2)
        ax.grid(alpha=0.3)
        paths.append(out_dir / "velocities.png")
        fig.tight_layout()
        fig.savefig(paths[-1], dpi=110)
        plt.close(fig)
    return paths
