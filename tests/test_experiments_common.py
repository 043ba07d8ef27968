"""The experiments' shared command line and report templates (``experiments/common.py``), and
real_flights' held-out section formatted from numbers alone (no estimator runs)."""

from __future__ import annotations

from dataclasses import replace
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


def test_real_flights_sections_are_formatted_from_their_numbers():
    """Each part of real_flights' report formats typed-in numbers without running anything;
    each cell checked is what they give (e.g. traffic's 500 µs per scan over 2 µs: 250×; the
    spread of 70 and 72 m: 71.0 ± 1.0; of 1, 2, 4 m: mean 2.3, half the range 1.5)."""
    from collections import Counter

    from experiments import real_flights as rf
    from torchsvs.datasets.flights import FlightReport
    from torchsvs.datasets.rows import RowReport

    rows = RowReport(10, 6, 3, Counter({"on ground": 1}), Counter({"time jump": 2}), 2)
    loader = "\n".join(rf.loader_lines(FlightReport(3, 2, {"a.json": "no positions"}, rows)))
    assert (
        "3 files: 2 read as tracks, 1 not track files (`a.json`: no positions). 2 tracks" in loader
    )
    assert (
        "10 rows: 6 measurements, 3 without a position (estimated as predictions), 1 set aside."
        in loader
    )
    assert "| set aside | on ground | 1 |\n| note | time jump | 2 |" in loader
    dirty = "\n".join(rf.dirty_lines([rf.DirtyFile("spoof.json", rows, False)]))
    assert dirty.startswith("## Dirty samples\n\nThe `noisy/` files")
    assert "| spoof.json | 10 | 2 | 6 | 3 | 1 | on ground 1, time jump 2 | NO |" in dirty

    speed = rf.Speed(5000, 25000, 500.0, 6, 72, [rf.SpeedRow("KS", 2.0, 4.0, 0.5, 40.0)], True, 0.0)
    text = "\n".join(rf.speed_lines(speed))
    assert "(best of 5 calls, one thread)" in text
    assert "(5000 one-second points for 25000 scans: 500 µs per scan)" in text
    assert "| KS | 2.00 | 250× | 4.00 | 125× | 0.50 | 1000× | 40.00 | 20× |" in text
    assert "float32, 6 realisations at once" in text and "as one batch (72 tracks)" in text
    assert "(`torchsvs.kernels.fused_axes`, loaded from the cache);" in text
    built = "\n".join(rf.speed_lines(replace(speed, build_seconds=12.34)))
    assert "built by the C++ compiler in 12.3 s on first use, then cached);" in built
    missing = "\n".join(rf.speed_lines(replace(speed, compiled=False, failure="no compiler")))
    assert "(`torchsvs.kernels.fused_axes`, unavailable: no compiler);" in missing

    scores = {
        "measurements": [70.0, 72.0],
        "KS": [30.0],
        "SVSS lag 5": [],
        "SVSTPS lag 5": [1.0, 2.0, 4.0],
        "traffic": [],
    }
    noise = "\n".join(rf.noise_lines(rf.Noise(2, 5, {50.0: scores}, {50.0: [1.5, -0.25]})))
    assert noise.startswith("## Noise levels (2 noise seeds each; learned rows: SURE on the")
    assert "| 50 | 71.0 ± 1.0 | 30.0 | — | 2.3 ± 1.5 | — |" in noise
    assert "SVSS lag 5 minus KS, per seed (m): σ = 50: +1.50, -0.25." in noise

    row = rf.WhyRow("KS", "full interval", {"position": 40.126, "velocity_motion": 6.04}, 1.26)
    why = "\n".join(rf.why_lines(rf.Why([row], 6.54, 41.0, 2.46, 39.5, 3.0)))
    assert why.startswith("## What decides the SVSF family against the KS\n")
    assert "| KS | full interval | 40.13 | 6.0 | 1.3 |" in why
    assert (
        "Adam at lr 0.05 for 40 steps reaches q = 6.5 (41.00 m held out); L-BFGS with the "
        "start search reaches q = 2.5 (39.50 m) in 3.0 s." in why
    )


def test_real_flights_imm_section_and_ranking_are_formatted_from_their_numbers():
    """The IMM's rows and section from typed-in numbers, merged into a small held-out table:
    ranked by position (SVSS 30, KS 40, learned IMM 44, IMM 45.5, SVSF 50, KF 60), the
    learned IMM is 3rd of 6, behind 1 of the 2 SVSF-family rows and first of the 4 filters."""
    from experiments import real_flights as rf
    from torchsvs.evaluation import markdown_table

    scores = {(0.03, 0.3): [(41.04, 5.16)], (1.0, 0.3): [(53.8, 6.7)]}
    defaults = rf.ImmDefaults(scores, [100.0], {100.0: 1.004})
    imm_rows = [
        rf.Row(
            rf.IMM_LABEL,
            "rules of thumb",
            None,
            {"position": 45.5, "velocity": 1.0, "velocity_motion": 7.5},
        ),
        rf.Row(
            rf.IMM_LABEL,
            "learned, SURE (σ known)",
            None,
            {"position": 44.0, "velocity": 1.0, "velocity_motion": 7.0},
        ),
    ]
    cli = {"position": 36.3, "seconds": 4.24}
    rows, section = rf.imm_lines(rf.Imm(imm_rows, "q 3 in 1 s", 100.0, cli, 32.55, defaults))
    assert rows[1] == [rf.IMM_LABEL, "learned, SURE (σ known)", "44.0", "1.0", "7.0", "", ""]
    assert section[0] == f"## {rf.IMM_LABEL}: a constant-velocity and a coordinated-turn mode"
    assert "IMM_RANKING" in section
    text = "\n".join(section)
    assert "flights (`--fit`: q 3 in 1 s)." in text
    assert (
        "--lag 0 --meas-std 100 --fit` on the held-out flights themselves: 36.30 m in 4.2 s" in text
    )
    assert "needing their truth: 32.55 m)." in text
    assert "| 0.03 | 0.3 | 41.0 | 5.2 |\n| 1 | 0.3 | 53.8 | 6.7 |" in text
    assert (
        "The defaults (0.03, 0.3) against the best of this grid, position RMSE ratio: σ = " in text
    )
    assert "ratio: σ = 100: 1.004. A velocity error" in text

    held_out = markdown_table(
        list(rf.HELD_OUT_COLUMNS),
        [
            ["measurements", "—", "70.7", "", "", "", ""],
            ["KS", "learned, SURE (σ known)", "40.0", "5.0", "6.0", "", ""],
            ["SVSS lag 5", "learned, SURE (σ known)", "30.0", "4.0", "4.5", "", ""],
            ["SVSF", "rules of thumb", "50.0", "6.0", "7.0", "", ""],
            ["KF", "rules of thumb", "60.0", "7.0", "8.0", "", ""],
        ],
    )
    report = rf.merge_imm(
        f"## Held-out flights, σ = 100 m\n\n{held_out}\n\n## Noise\n", rows, section
    )
    assert (
        "the learned IMM ranks 3 of 6 rows (44.0 m): behind the learned KS (rank 2, 40.0 m) and 1 "
        "of the 2 rows of the SVSF family (the best SVSS lag 5, 30.0 m), ahead of 1 of them (the "
        "SVSF filter rows, 50.0 m, among them)." in report
    )
    assert "Among the filters (IMM(CV, CT), KF, SVSF) the learned IMM ranks 1 of 4." in report
    assert "| 3 | IMM(CV, CT) | learned, SURE (σ known) | 44.0 | 7.0 |" in report
    assert "IMM_RANKING" not in report and "$" not in report
