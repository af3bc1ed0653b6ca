"""The figures' writer draws each figure once."""
from __future__ import annotations

from services.servo import figures as plots


def test_a_figure_is_laid_out_and_drawn_once_when_saved(tmp_path, monkeypatch):
    plt = plots.pyplot()
    from matplotlib.figure import Figure

    draws = []
    draw = Figure.draw
    monkeypatch.setattr(Figure, "draw", lambda self, renderer: draws.append(1) or draw(self, renderer))
    fig, (top, bottom) = plt.subplots(2, 1, sharex=True)
    top.plot([0, 1, 2], [1, 3, 2], label="a")
    top.legend()
    bottom.semilogy([0, 1, 2], [1e-3, 1e-1, 1.0])
    paths: list = []
    plots.save(fig, tmp_path / "figure.png", paths)
    assert paths == [tmp_path / "figure.png"] and (tmp_path / "figure.png").stat().st_size > 0
    assert len(draws) == 1  # tight_layout's own measuring is no draw; savefig's dry run would be a second
