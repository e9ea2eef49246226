"""The figures of a large network's run: drawn without a warning (pytest turns warnings into
errors) and with a legend a reader can hold: at most :data:`LEGEND_MAX` entries, the last one
saying how many more sensors are drawn."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from matplotlib import pyplot as plt

from covnet import kinds
from covnet.cli.app import main
from covnet.covariance_control import plots
from covnet.covariance_control.network_sizes import bench_config

PAPER = Path(__file__).resolve().parents[2] / "configs" / "paper.yaml"


@pytest.mark.parametrize("n", [8, 64, 256])
def test_a_large_networks_figures_have_a_legend_that_fits(tmp_path, capsys, monkeypatch, n):
    _, sc = kinds.load(PAPER)
    cfg = tmp_path / f"net{n}.yaml"
    cfg.write_text(yaml.safe_dump(bench_config(sc, n, 3), sort_keys=False))
    legends: list[list[str]] = []
    save = plt.Figure.savefig

    def spy(fig, *args, **kwargs):
        if Path(args[0]).name == "fig1_sensor_ellipses.png":
            for ax in fig.axes:
                if (leg := ax.get_legend()) is not None:
                    legends.append([t.get_text() for t in leg.get_texts()])
        return save(fig, *args, **kwargs)

    monkeypatch.setattr(plt.Figure, "savefig", spy)
    assert main(["run", str(cfg), "--out", str(tmp_path / "out")]) == 0
    assert "Warning" not in capsys.readouterr().err
    (texts,) = legends
    assert len(texts) == min(n, plots.LEGEND_MAX)
    if n <= plots.LEGEND_MAX:
        assert texts == [f"S{1 + i % 8}.{1 + i // 8}" for i in range(n)]
    else:
        assert texts[-1] == f"and {n - plots.LEGEND_MAX + 1} more"
        assert texts[:-1] == [f"S{1 + i % 8}.{1 + i // 8}" for i in range(plots.LEGEND_MAX - 1)]


def test_target_colours_are_all_different():
    for n in (1, 6, 8, 10, 11, 20, 21, 40):
        cols = plots.target_colours(n)
        assert len(cols) == n and len(set(cols)) == n, n
    assert plots.target_colours(8)[:6] == plots.target_colours(6)  # a target keeps its colour


def test_the_assignment_raster_keys_every_target_in_its_own_colour(tmp_path, monkeypatch, capsys):
    """configs/large_multitarget.yaml: 8 targets, 64 sensors.  Six colours repeated gave T7
    T1's red and T8 T2's blue, named only in a title cut off at the figure's edge."""
    raw = yaml.safe_load((PAPER.parent / "large_multitarget.yaml").read_text())
    raw["scans"] = 2
    cfg = tmp_path / "lmt.yaml"
    cfg.write_text(yaml.safe_dump(raw, sort_keys=False))
    keys: list[list[tuple[str, tuple[float, ...]]]] = []
    save = plt.Figure.savefig

    def spy(fig, *args, **kwargs):
        if Path(args[0]).name == "fig_assignment_raster.png":
            for ax in fig.axes:
                leg = ax.get_legend()
                assert leg is not None
                keys.append(
                    [(t.get_text(), tuple(h.get_facecolor()))
                     for t, h in zip(leg.get_texts(), leg.legend_handles, strict=True)]
                )  # fmt: skip
        return save(fig, *args, **kwargs)

    monkeypatch.setattr(plt.Figure, "savefig", spy)
    assert main(["run", str(cfg), "--out", str(tmp_path / "out")]) == 0
    assert "Warning" not in capsys.readouterr().err
    assert keys
    for key in keys:
        names = [name for name, _ in key]
        assert names == [t["id"] for t in raw["targets"]] + ["off"]
        assert len({colour for _, colour in key}) == len(key)


def test_the_scene_legend_hides_no_sensor(tmp_path, monkeypatch, capsys):
    """configs/large_multitarget.yaml's scene: the targets' key sat inside the axes, in the
    lower right corner, over sensors P40 and P60 and their names.  No sensor's marker may lie
    under the legend."""
    raw = yaml.safe_load((PAPER.parent / "large_multitarget.yaml").read_text())
    raw["scans"] = 2
    cfg = tmp_path / "lmt.yaml"
    cfg.write_text(yaml.safe_dump(raw, sort_keys=False))
    hidden: list[str] = []
    checked = []
    save = plt.Figure.savefig
    sensors = [(s["id"], s["position_m"]) for s in raw["sensors"]]

    def spy(fig, *args, **kwargs):
        if Path(args[0]).name == "fig_scene.png":
            fig.canvas.draw()
            for ax in fig.axes:
                leg = ax.get_legend()
                assert leg is not None
                box = leg.get_window_extent()
                for sid, (x, y) in sensors:
                    px, py = ax.transData.transform((x / 1e3, y / 1e3))
                    if box.contains(px, py):
                        hidden.append(sid)
                checked.append(len(sensors))
        return save(fig, *args, **kwargs)

    monkeypatch.setattr(plt.Figure, "savefig", spy)
    assert main(["run", str(cfg), "--out", str(tmp_path / "out")]) == 0
    assert "Warning" not in capsys.readouterr().err
    assert checked == [64] and hidden == []


def test_the_surveillance_scene_keeps_its_edge_sensors_clear_of_the_title(
    tmp_path, monkeypatch, capsys
):
    """configs/surveillance.yaml puts radars on the area's corners and edges (R3, R4, B3 on its
    top): with the axes ending at the area, their names ran into the title.  Every sensor
    lies inside the drawn limits, and no sensor's name overlaps the title."""
    raw = yaml.safe_load((PAPER.parent / "surveillance.yaml").read_text())
    cfg = PAPER.parent / "surveillance.yaml"
    ids = {s["id"] for s in raw["sensors"]}
    seen: list[str] = []
    save = plt.Figure.savefig

    def spy(fig, *args, **kwargs):
        if Path(args[0]).name == "fig_scene.png":
            renderer = fig.canvas.get_renderer()
            fig.canvas.draw()
            (ax,) = fig.axes
            title = ax.title.get_window_extent(renderer)
            (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
            for s in raw["sensors"]:
                x, y = s["position_m"]
                assert x0 < x < x1 and y0 < y < y1, s["id"]
            for text in ax.texts:
                if text.get_text() in ids:
                    seen.append(text.get_text())
                    assert not text.get_window_extent(renderer).overlaps(title), text.get_text()
        return save(fig, *args, **kwargs)

    monkeypatch.setattr(plt.Figure, "savefig", spy)
    assert main(["run", str(cfg), "--out", str(tmp_path / "out")]) == 0
    assert "Warning" not in capsys.readouterr().err
    assert sorted(seen) == sorted(ids)


def test_the_scene_draws_each_sensors_coverage_at_its_place_in_km(tmp_path, monkeypatch):
    """The many-target scene's coverage outlines were drawn in metres on the kilometre axes:
    each circle 1000 times too large and too far out, so none was seen (and drawing their
    dashes took most of the figures' time: 5.5 s of 7 at 64 sensors)."""
    from matplotlib.patches import Wedge

    raw = yaml.safe_load((PAPER.parent / "large_multitarget.yaml").read_text())
    raw["scans"] = 2
    cfg = tmp_path / "lmt.yaml"
    cfg.write_text(yaml.safe_dump(raw, sort_keys=False))
    out = tmp_path / "out"
    assert main(["run", str(cfg), "--out", str(out), "--no-figures"]) == 0
    want = sorted(
        (round(s["position_m"][0] / 1e3, 6), round(s["position_m"][1] / 1e3, 6),
         round(s["max_range_m"] / 1e3, 6))  # fmt: skip
        for s in raw["sensors"]
        if s.get("max_range_m")
    )
    got: list[list[tuple[float, float, float]]] = []

    def spy(fig, *args, **kwargs):
        if Path(args[0]).name == "fig_scene.png":
            for ax in fig.axes:
                w = [p for p in ax.patches if isinstance(p, Wedge)]
                got.append(sorted((round(p.center[0], 6), round(p.center[1], 6),
                                   round(p.r, 6)) for p in w))  # fmt: skip
        return None

    monkeypatch.setattr(plt.Figure, "savefig", spy)
    assert main(["plot", str(out)]) == 0
    assert got and all(g == want for g in got) and len(want) == 64
