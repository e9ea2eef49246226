"""Write ``covnet-layout.json``, the Foxglove layout for covnet's visual channels, with the
Foxglove SDK's layout types (``foxglove.layouts``): ``python docs/foxglove/make_layout.py``.

The 3D panel shows ``/covnet/scene``; the plots read ``/covnet/scan`` (``covnet.ScanMetrics``);
the log panel shows ``/covnet/log``.  ``tests/unit/test_visual.py`` checks that the committed
file is what this script writes and that every topic and field it names exists.
"""

from __future__ import annotations

import json
from pathlib import Path

import foxglove.layouts as fl

HERE = Path(__file__).resolve().parent
SCAN = "/covnet/scan"


def _plot(title: str, *series: tuple[str, str]) -> fl.PlotPanel:
    return fl.PlotPanel(
        title=title,
        config=fl.PlotConfig(
            paths=[fl.PlotSeries(value=f"{SCAN}.{field}", label=label) for field, label in series],
            show_legend=True,
        ),
    )


def layout() -> fl.Layout:
    scene = fl.ThreeDeePanel(
        title="covnet scene",
        config=fl.ThreeDeeConfig(
            topics={"/covnet/scene": fl.BaseRendererSceneUpdateTopicSettings(visible=True)},
        ),
    )
    plots = fl.SplitContainer(
        direction="column",
        items=[
            fl.SplitItem(
                content=_plot("tr P and tr P_d", ("trace_P", "tr P"), ("trace_Pd", "tr P_d"))
            ),
            fl.SplitItem(
                content=_plot("f(P, P_d) and N_k", ("f", "f(P, P_d)"), ("n_active", "N_k"))
            ),
            fl.SplitItem(content=_plot("RMSE so far and NEES", ("rmse", "RMSE"), ("nees", "NEES"))),
            fl.SplitItem(
                content=_plot(
                    "network",
                    ("scan_latency_ms", "scan latency [ms]"),
                    ("measurement_latency_ms", "measurement latency [ms]"),
                    ("messages", "messages per scan"),
                )
            ),
        ],
    )
    log = fl.LogPanel(title="status", config=fl.LogConfig(topic_to_render="/covnet/log"))
    return fl.Layout(
        content=fl.SplitContainer(
            direction="row",
            items=[
                fl.SplitItem(
                    proportion=3,
                    content=fl.SplitContainer(
                        direction="column",
                        items=[
                            fl.SplitItem(proportion=4, content=scene),
                            fl.SplitItem(content=log),
                        ],
                    ),
                ),
                fl.SplitItem(proportion=2, content=plots),
            ],
        )
    )


def text() -> str:
    return json.dumps(json.loads(layout().to_json()), indent=2, sort_keys=True) + "\n"


if __name__ == "__main__":
    (HERE / "covnet-layout.json").write_text(text())
    print(HERE / "covnet-layout.json")
