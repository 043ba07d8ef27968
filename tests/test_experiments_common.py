"""The experiments' shared command line and report templates (``experiments/common.py``), and
real_flights' held-out section formatted from numbers alone (no estimator runs)."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import pytest

from experiments import common


def test_templates_split_into_sections_and_refuse_missing_fields(tmp_path, monkeypatch):
    (tmp_path / "toy.md").write_text(
        "<!-- a comment for the reader: $not_a_field -->\n"
        "<!-- section: report -->\n# $title\n\n$body\n"
        "<!-- section: row -->\n- $item costs $$$price\n"
    )
    monkeypatch.setattr(common, "TEMPLATES", tmp_path)
    sections = common.template("toy")
    assert set(sections) == {"report", "row"}  # the text before the first section is not one
    assert common.render("toy", "report", title="T", body="b") == "# T\n\nb"
    assert common.render("toy", "row", item="x", price=3) == "- x costs $3"
    with pytest.raises(KeyError, match="body"):
        common.render("toy", "report", title="T")
    with pytest.raises(ValueError, match="^name: expected a template"):
        common.template("missing")
    (tmp_path / "bare.md").write_text("no sections\n")
    with pytest.raises(ValueError, match="^name: .* has no '<!-- section"):
        common.template("bare")


def test_every_template_of_the_checkout_has_sections():
    names = sorted(p.stem for p in common.TEMPLATES.glob("*.md"))
    assert {"svss_paper", "road_tracking", "real_flights"} <= set(names)
    for name in names:
        assert common.template(name)


def test_main_runs_compute_figures_report_and_writes_the_report(tmp_path, capsys):
    seen = {}

    def compute(args):
        seen["args"] = args
        return {"runs": args.runs, "seed": args.seed}

    def figures(res, out):
        assert out == tmp_path
        return ["toy.png"]

    def report(res, pngs):
        return f"runs {res['runs']}, seed {res['seed']}, {pngs}\n"

    res = common.main(
        "toy",
        "A toy experiment.\n\nMore.",
        compute,
        figures,
        report,
        runs=7,
        options=lambda p: p.add_argument("--quick", action="store_true"),
        argv=["--seed", "3", "--quick", "--out", str(tmp_path)],
    )
    assert res == {"runs": 7, "seed": 3} and seen["args"].quick
    assert (tmp_path / "toy.md").read_text() == "runs 7, seed 3, ['toy.png']\n"
    assert f"written: {tmp_path / 'toy.md'} and toy.png" in capsys.readouterr().out


def test_main_help_names_the_module_and_each_experiments_default(capsys):
    with pytest.raises(SystemExit):
        common.main("toy", "A toy.", dict, list, str, runs=40, argv=["--help"])
    out = capsys.readouterr().out
    assert out.startswith("usage: python -m experiments.toy")
    assert "Monte Carlo runs (default 40)" in out and "random seed (default 0)" in out


def test_real_flights_held_out_section_is_formatted_from_its_numbers():
    """held_out_lines formats a HeldOut without running anything: the values below are typed
    in, and each cell checked is what they give (e.g. `track --fit`'s ratio 41.8 / 38 = 1.100,
    the learned KS's 40 / 38 = 1.053 of its best grid q)."""
    from experiments.real_flights import HeldOut, Row, held_out_lines

    fit = SimpleNamespace(seconds=1.25, stages=["q 3.0"], settings=None)
    ks = {"position": 40.0, "velocity": 5.0, "velocity_motion": 6.0}
    svss = {"position": 30.0, "velocity": 4.0, "velocity_motion": 4.5, "us_per_point": 1.234}
    study = HeldOut(
        sigma=100.0,
        lag=5,
        measurements={"position": 70.71},
        rows=[
            Row("KS", "learned, SURE (σ known)", None, ks),
            Row("SVSS lag 5", "learned, SURE (σ known)", None, svss),
        ],
        fits={"KS, learned, SURE (σ known)": fit, "SVSS lag 5, learned, SURE (σ known)": fit},
        ks_test={2.0: 38.0, 4.0: 39.0},
        sv_test={(2.0, 300.0): 25.0},
        clis={"ks": {"position": 41.8, "seconds": 2.0}, "svss": {"position": 27.5, "seconds": 3.0}},
    )
    text = "\n".join(held_out_lines(study))
    assert text.startswith("## Held-out flights, σ = 100 m\n\nPosition RMSE per axis")
    assert "| measurements | — | 70.7 |  |  |  |  |" in text
    assert "| KS | learned, SURE (σ known) | 40.0 | 5.0 | 6.0 |  |  |" in text
    assert "| SVSS lag 5 | learned, SURE (σ known) | 30.0 | 4.0 | 4.5 | 1.23 |  |" in text
    assert "Learned KS (SURE): 1.053 of its best grid q" in text
    assert "learned SVSS lag 5 (SURE): 1.200 of its best grid ψ." in text
    assert "--estimator NAME --meas-std 100 --fit` on a CSV" in text
    assert "| KS | 41.80 | 38.00 | 1.100 | 2.0 |" in text
    assert "| SVSS | 27.50 | 25.00 | 1.100 | 3.0 |" in text
    assert text.endswith("| SVSS | 27.50 | 25.00 | 1.100 | 3.0 |\n")
    assert study.results["KS, learned, SURE (σ known)"] is ks


def test_the_experiments_write_where_python_m_writes():
    from experiments import imm_svsf_kf, ksvd_paper, road_tracking, spvsf_paper, svss_paper

    for module in (svss_paper, road_tracking, imm_svsf_kf, ksvd_paper, spvsf_paper):
        assert module.RESULTS == Path(module.__file__).parent / "results"
