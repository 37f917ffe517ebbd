"""The registration's figures (register/plots.py): each stage on its own panel, none for a stage
that did not run."""

from __future__ import annotations

import numpy as np
from PIL import Image

from register.plots import _stage_kind, convergence_plot


def test_history_stages_are_sorted_by_kind():
    kinds = [_stage_kind(s) for s in ("contextual", "search", "level0", "finalist2.level0", "polish",
                                      "restart1.level1", "restart1.polish")]
    assert kinds == ["network", "search", "refine", "refine", "polish", "refine", "polish"]


def test_the_network_gets_its_own_panel_and_a_method_without_it_has_one_panel(tmp_path):
    refine = [("level0", 0.5 + 0.01 * i, [0] * 6) for i in range(20)] + [("polish", 0.7, [0] * 6)]
    network = [("contextual", -v, [0] * 6) for v in np.geomspace(20, 0.1, 15)]
    convergence_plot(network + [("search", 0.6, [0] * 6)] + refine, tmp_path / "both.png", title="verdict: x",
                     search_status="skipped (network pose scored 0.90 >= 0.85)")
    convergence_plot(refine, tmp_path / "one.png")
    both, one = Image.open(tmp_path / "both.png"), Image.open(tmp_path / "one.png")
    assert both.size[0] > 1.8 * one.size[0]  # two panels side by side against one
    convergence_plot(network, tmp_path / "net.png")  # the network alone: its one panel
    assert Image.open(tmp_path / "net.png").size == one.size


def test_a_search_again_by_local_similarity_gets_its_own_panel(tmp_path):
    refine = [("level0", 0.5 + 0.01 * i, [0] * 6) for i in range(20)] + [("polish", 0.93, [0] * 6)]
    network = [("contextual", -v, [0] * 6) for v in np.geomspace(20, 0.1, 15)]
    rescue = ([("rescue.search", 0.3 + 0.02 * i, [0] * 6) for i in range(8)]
              + [(f"rescue.finalist{k}.level1", 0.4 + 0.01 * i + 0.1 * k, [0] * 6) for k in range(3) for i in range(10)])
    convergence_plot(network + [("search", 0.6, [0] * 6)] + refine, tmp_path / "two.png")
    convergence_plot(network + [("search", 0.6, [0] * 6)] + refine + rescue, tmp_path / "three.png")
    two, three = Image.open(tmp_path / "two.png"), Image.open(tmp_path / "three.png")
    assert three.size[0] > 1.4 * two.size[0]  # a third panel: its own scale (local similarity)
