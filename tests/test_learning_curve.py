"""benchmarks/learning_curve.py: the power law through a run's validation checks, and the pairs it
would take to reach an error."""

from __future__ import annotations

import math

import pytest

from tests.conftest import load_benchmark


@pytest.fixture(scope="module")
def lc():
    return load_benchmark("learning_curve")


def test_the_fit_recovers_a_power_law_and_where_it_reaches_the_target(lc):
    """error = 100 N^-0.3 exactly: b = 0.3 and N* = (100 / 10)^(1 / 0.3) = 2.15e3 (closed form),
    to 1e-9 relative; one spike (a check at twice the law) does not move the Theil-Sen fit by
    more than 0.01 in b."""
    pairs = [1000.0 * 1.5 ** i for i in range(12)]
    errors = [100 * n ** -0.3 for n in pairs]
    f = lc.fit(pairs, errors, 10.0)
    assert f["b"] == pytest.approx(0.3, rel=1e-9)
    assert f["n_star"] == pytest.approx(10 ** (1 / 0.3), rel=1e-9)
    assert f["fitted"] == pytest.approx(errors[-1], rel=1e-9)
    spiked = list(errors)
    spiked[7] *= 2
    assert lc.fit(pairs, spiked, 10.0)["b"] == pytest.approx(0.3, abs=0.01)
    flat = lc.fit(pairs, [20.0 + 0 * n for n in pairs], 10.0)
    assert math.isinf(flat["n_star"])


def test_the_table_fits_the_first_lr_only_and_refuses_a_foreign_file(lc, tmp_path, capsys):
    log = tmp_path / "log.csv"
    rows = ["iteration,lr,val_rot_err_deg"]
    rows += [f"{i},0.001,{100 * (i * 256) ** -0.3}" for i in range(500, 6001, 500)]
    rows += ["6500,0.0003,3.0"]
    log.write_text("\n".join(rows) + "\n")
    # 100 N^-0.3 = 1 at N = 100^(1 / 0.3) = 4.6 M; the check after the lr step is listed, not fitted
    assert lc.main([str(log), "--groups", "all", "--from-pairs", "0", "--target-deg", "1"]) == 0
    out = capsys.readouterr().out
    assert "| 12 (0.1 M-1.5 M) | 0.30 (0.30-0.30) | 1.4 deg | 4.6 M (4.6 M-4.6 M) |" in out and "| 3.0 at 1.7 M |" in out
    bad = tmp_path / "other.csv"
    bad.write_text("a,b\n1,2\n")
    with pytest.raises(SystemExit, match="not a ctxreg train log.csv"):
        lc.main([str(bad)])
