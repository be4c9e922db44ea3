"""The Allan plot's slope guides (-1, -1/2, 0, +1/2, +1: Q, N, B, K, R) can be read: each of the
five is labelled inside the plotted area and no two labels overprint (issue 15, "plots people
read"). Before, every label sat at the guide's right end: the falling guides (-1, -1/2) end
below the plot and their labels were clipped away, the others were stacked where they meet.
The curves are IEEE 952 sums written out here (white + flicker + random walk; a floor at the
end; a rising curve), with a +-20 % band standing in for the 95 % band."""
from __future__ import annotations

import math

import numpy as np
import pytest

matplotlib = pytest.importorskip("matplotlib")
matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from rigctl.report.report_plots import draw_allan_axis  # noqa: E402

TAU = 0.01 * 2.0 ** np.arange(0, 17)  # 0.01 .. 655 s
CURVES = {
    "V with a floor": (0.15, 2.8, 1.0),      # N deg/sqrt(h), B deg/h, K deg/h/sqrt(h)
    "floor to the end": (0.15, 2.8, 0.0),
    "random walk rising": (0.05, 0.0, 3600.0),
}


def _curve(n: float, b: float, k: float) -> np.ndarray:
    n_s, k_s = n * 60.0, k / 60.0  # N deg/sqrt(h) -> deg/h sqrt(s), K deg/h/sqrt(h) -> deg/h/sqrt(s)
    return np.sqrt(n_s ** 2 / TAU + (0.664 * b) ** 2 + k_s ** 2 * TAU / 3.0)


@pytest.mark.parametrize("name", list(CURVES))
def test_each_slope_guide_is_labelled_inside_the_plot_without_overlap(name: str) -> None:
    dev = _curve(*CURVES[name])
    fig, ax = plt.subplots(figsize=(5.5, 3.3))
    try:
        draw_allan_axis(ax, TAU, dev, None, "gyro", "deg/h", 1.0, name,
                        lo95=0.8 * dev, hi95=1.2 * dev)
        fig.tight_layout()
        fig.canvas.draw()
        renderer = fig.canvas.get_renderer()
        labels = {t.get_text(): t for t in ax.texts if t.get_text().startswith("slope ")}
        assert sorted(labels) == sorted(["slope -1 (Q)", "slope -1/2 (N)", "slope 0 (B)",
                                         "slope +1/2 (K)", "slope +1 (R)"])
        box = ax.get_window_extent(renderer)
        extents = {}
        for text, t in labels.items():
            x, y = ax.transData.transform(t.xy)  # the anchor, inside the axes (else clipped)
            assert box.x0 <= x <= box.x1 and box.y0 <= y <= box.y1, (text, t.xy, ax.get_ylim())
            e = t.get_window_extent(renderer)
            assert box.x0 - 1 <= e.x0 and e.x1 <= box.x1 + 1, (text, e, box)
            assert box.y0 - 1 <= e.y0 and e.y1 <= box.y1 + 1, (text, e, box)
            extents[text] = e
        names = list(extents)
        for i, a in enumerate(names):
            for b in names[i + 1:]:
                assert not extents[a].overlaps(extents[b]), (a, b, extents[a], extents[b])
        # each guide has the slope it is labelled with: read off its line here
        guides = [ln for ln in ax.get_lines() if ln.get_linestyle() == ":" and ln.get_color() == "0.55"]
        slopes = sorted(round(math.log(ln.get_ydata()[1] / ln.get_ydata()[0])
                              / math.log(ln.get_xdata()[1] / ln.get_xdata()[0]), 6) for ln in guides)
        assert slopes == [-1.0, -0.5, 0.0, 0.5, 1.0]
    finally:
        plt.close(fig)
