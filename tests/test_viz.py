"""Overlay images and the HTML report."""

from __future__ import annotations

import numpy as np

from ssp.geometry import make_pose
from ssp.library import ObjectLibrary
from ssp.sim.render import Camera, look_at, render
from ssp.viz.overlay import METHOD_COLOURS, overlay, save_png
from ssp.viz.report import markdown_tables_to_html, write_html_report

LIB = ObjectLibrary.builtin()
CAM = Camera.default().subsample(4)
T_WC = look_at([0.0, -0.5, 0.5], [0.0, 0.0, 0.0])


def _truth(x=0.0):
    return [("cube", make_pose(t=[x, 0.0, 0.0254]))]


def test_overlay_draws_truth_and_estimates_where_they_are():
    depth = render([("c", LIB["cube"].mesh, _truth()[0][1])], T_WC, CAM).depth
    same = overlay(LIB, depth, CAM, T_WC, _truth(), {"ssp": _truth()}, crop=False)
    off = overlay(LIB, depth, CAM, T_WC, _truth(), {"ssp": _truth(0.02)}, crop=False)
    green = np.array(METHOD_COLOURS["ssp"])
    n_same = int(np.all(same == green, axis=2).sum())
    n_off = int(np.all(off == green, axis=2).sum())
    assert np.all(same == 255, axis=2).sum() > 20  # the truth outline
    assert n_off > 3 * max(n_same, 1)  # a 2 cm shifted estimate shows its own outline
    cropped = overlay(LIB, depth, CAM, T_WC, _truth(), {"ssp": _truth()})
    assert max(cropped.shape[:2]) >= 240 and cropped.shape[2] == 3


def test_report_html_has_the_table_and_images(tmp_path):
    img = np.zeros((20, 30, 3), np.uint8)
    png = save_png(tmp_path / "frames" / "f0.png", img, "frame 0", ["truth", "ssp"])
    md = "# Results\n\n| method | error |\n|---|---|\n| ssp | 1.0 mm |\n| estimator | 4 mm |\n"
    page = write_html_report(tmp_path, "demo", md, frames=[("frame 0", png)], notes=["cmd"])
    text = page.read_text()
    assert "<td>ssp</td><td>1.0 mm</td>" in text and "<th>method</th>" in text
    assert "src='frames/f0.png'" in text
    assert "<h2>Results</h2>" in markdown_tables_to_html(md)
