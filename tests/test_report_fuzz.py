"""Issue 41: train/report.py's loaders, fuzzed with hypothesis, and its command line on a damaged run.

The files report.py reads: a run's config.json, metrics.json and curves.jsonl (train/report.py load_run, the
one loader of a run directory and of a report's copy of one under <report>/runs; results.curves.read_curves;
results.plots.read_run, what its learning curves are drawn from) and an earlier report's stats.json
(--from-stats: read_stats). Each is fed random bytes, truncations, bytes flipped, bad UTF-8, keys removed,
values of other types (also nested: an episode's world outcomes, the paired gain), bare NaN and numbers
too large for a float. The property, as in tests/test_loader_fuzz.py: the loader returns what its callers
can use (the cells, the tables, the prior's gain rows and the curves are formed from it without an error)
or raises ValueError, the project's one error type, in one line naming the file. The command line then
turns that line into `report.py: error: <line>`, exit 2, nothing written.

Small synthetic runs written here: no training, no Warp; bounded and derandomized.
"""

from __future__ import annotations

import copy
import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scripts import ROOT, load_script
from test_loader_fuzz import FUZZ, JSON, damaged_bytes, json_file, refused_or_valid, truncation

from vkgrl_newton._io import strict_json
from vkgrl_newton.results.curves import CURVE_KEYS, CURVES_FILE, CurveWriter, read_curves
from vkgrl_newton.results.plots import mean_std, read_run

# a damaged curve's success all null: report.py's training-success means are NaN (numpy warns; the report shows a dash)
pytestmark = pytest.mark.filterwarnings("ignore:Mean of empty slice:RuntimeWarning")
CONFIG = {"task": "PegInsert", "method": "kgrl", "env": "factory", "action_dim": 4, "seed": 0, "num_envs": 2,
          "preset": "quick", "time_obs": True, "obs_dim": 8, "sac": {"batch_size": 256}, "total_steps": 15_000,
          "checkpoint_every": 4800, "device": "cpu", "label": "lab"}
ROUNDS = [{"world_success": [1.0, 0.0]}, {"world_success": [1.0, None]}]  # None: a world lost to a blow-up
METRICS = {"success_rate": 0.5, "mean_contact_force": 1.0, "mean_episode_reward": 10.0,
           "time_to_first_success_s": None, "training": {"wall_s": 900.0}, "wall_s": 300.0, "eval_seed": 10_000,
           "per_episode": ROUNDS, "prior_eval": {"success_rate": 0.25, "per_episode": [
               {"world_success": [1.0, 0.0]}, {"world_success": [0.0, 0.0]}]},
           "paired_gain": {"success_rate": {"mean": 0.25, "ci_low": 0.0, "ci_high": 0.5, "n_pairs": 3}}}
# the nested places of metrics.json that the report reads
NESTED = (("per_episode", 0, "world_success", 1), ("per_episode", 1, "world_success"), ("per_episode", 0),
          ("prior_eval", "per_episode", 1, "world_success", 0), ("prior_eval", "success_rate"),
          ("paired_gain", "success_rate", "mean"), ("paired_gain", "success_rate"), ("training", "wall_s"))
CURVE = dict(episode_reward=1.0, success_rate=0.5, success_rate_any=0.5, mean_contact_force=1.0,
             peak_contact_force=2.0, time_to_first_success_s=math.nan, wall_s=1.0)


@pytest.fixture(scope="module")
def report_py():
    return load_script("report")


def write_run(run_dir: Path, config: dict = CONFIG, metrics: dict = METRICS) -> Path:
    run_dir.mkdir(parents=True)
    (run_dir / "config.json").write_text(strict_json(config))
    (run_dir / "metrics.json").write_text(strict_json(metrics))
    curves = CurveWriter(run_dir)
    for t in (4800, 7200, 9600, 12000):
        curves.append(transitions=t, **CURVE)
    return run_dir


@pytest.fixture(scope="module")
def seed_run(tmp_path_factory) -> Path:
    return write_run(tmp_path_factory.mktemp("seed") / "PegInsert_factory_4d_kgrl+lab" / "seed0")


@pytest.fixture(scope="module")
def other_seed(tmp_path_factory) -> Path:
    """A good run of the seed run's cell, seed 1: the damaged run is read beside it."""
    return write_run(tmp_path_factory.mktemp("other") / "PegInsert_factory_4d_kgrl+lab" / "seed1",
                     {**CONFIG, "seed": 1})


def _valid_run(report_py, run_dir: Path, others: tuple[Path, ...] = ()):
    """What the report forms from an accepted run (beside good runs `others`), without an error: the cells,
    the tables, the IQM, the prior's gain rows, the method pairs, and the curves it draws."""
    def check(_):
        try:
            cells = report_py.load_cells([run_dir, *others])
        except report_py.MixedCellError as e:  # a run of another configuration than its cell's: the report says so
            assert "one cell holds runs that differ in their seed alone" in str(e) or "two runs of seed" in str(e), e
            assert "\n" not in str(e)
            cells = report_py.load_cells([run_dir])
        report_py.markdown_tables(cells, {})
        report_py.result_rows(cells, {})
        report_py.aggregate_stats(cells, reps=2)
        report_py.prior_gain_rows(cells, reps=2)
        report_py.method_pair_rows(cells, reps=2)
        config, curves = read_run(run_dir)
        for steps, values in curves.values():
            if len(steps):
                mean_std([(steps, values)])
    return check


def test_the_seed_run_loads_with_its_lost_world_as_nan(report_py, seed_run):
    config, metrics = report_py.load_run(seed_run)
    assert config["label"] == "lab" and metrics["per_episode"][1]["world_success"] == [1.0, None]
    (row,) = report_py.load_cells([seed_run])[("PegInsert", "factory", 4, "kgrl+lab")]
    assert np.isnan(row["outcomes"][3]) and row["paired"]["gain"]["mean"] == 0.25
    _valid_run(report_py, seed_run)(None)


@st.composite
def nested_mutation(draw, seed: dict) -> bytes:
    """metrics.json with one of the nested values the report reads replaced (any JSON, or a number too large
    for a float: 1e999 reads as inf), or removed."""
    obj = copy.deepcopy(seed)
    path = draw(st.sampled_from(NESTED))
    parent = obj
    for k in path[:-1]:
        parent = parent[k]
    op = draw(st.sampled_from(("replace", "drop", "huge")))
    if op == "drop":
        parent.pop(path[-1])
        return json.dumps(obj).encode()
    parent[path[-1]] = "HUGE" if op == "huge" else draw(JSON)
    return json.dumps(obj).encode().replace(b'"HUGE"', draw(st.sampled_from((b"1e999", b"-1e999", b"1" + b"0" * 400))))


@st.composite
def damaged_curves(draw) -> bytes:
    """curves.jsonl with a row replaced by any JSON or given a value of another type, bare NaN, a number too
    large for a float or bad UTF-8; or cut short, or random bytes."""
    rows = [{"transitions": 2400 * i, **{k: v for k, v in CURVE.items() if k != "time_to_first_success_s"}}
            for i in range(1, 4)]
    lines = [json.dumps(r).encode() for r in rows]
    i = draw(st.integers(0, len(lines) - 1))
    kind = draw(st.sampled_from(("row", "value", "constant", "huge", "utf8", "cut", "bytes")))
    if kind == "row":
        lines[i] = json.dumps(draw(JSON)).encode()
    elif kind == "value":
        rows[i][draw(st.sampled_from(CURVE_KEYS))] = draw(JSON)
        lines[i] = json.dumps(rows[i]).encode()
    elif kind in ("constant", "huge"):
        rows[i][draw(st.sampled_from(CURVE_KEYS))] = "X"
        lines[i] = json.dumps(rows[i]).encode().replace(b'"X"', draw(st.sampled_from(
            (b"NaN", b"Infinity", b"-Infinity") if kind == "constant" else (b"1e999", b"1" + b"0" * 400))))
    elif kind == "utf8":
        at = draw(st.integers(0, len(lines[i])))
        lines[i] = lines[i][:at] + draw(st.sampled_from((b"\xff", b"\xc3", b"\xed\xa0\x80"))) + lines[i][at:]
    data = b"\n".join(lines) + b"\n"
    if kind == "cut":
        return data[: draw(truncation(len(data)))]
    if kind == "bytes":
        return draw(damaged_bytes(data))
    return data


@st.composite
def mutated_values(draw, seed: dict, keys: tuple) -> bytes:
    """The seed with one of `keys` (what the report reads at the top level) of another type, removed, bare
    NaN or a number too large for a float."""
    obj = copy.deepcopy(seed)
    key = draw(st.sampled_from(keys))
    op = draw(st.sampled_from(("json", "drop", "text", "bool", "constant")))
    if op == "drop":
        obj.pop(key, None)
        return json.dumps(obj).encode()
    obj[key] = {"json": draw(JSON), "text": draw(st.sampled_from(("high", "0.5", "", "4"))), "bool": True,
                "constant": "X"}[op]
    text = json.dumps(obj).encode()
    return text.replace(b'"X"', draw(st.sampled_from((b"NaN", b"-Infinity", b"1e999", b"1" + b"0" * 400))))


DAMAGED = {"config.json": lambda: st.one_of(json_file(CONFIG), mutated_values(CONFIG, (
               "task", "method", "env", "action_dim", "seed", "label", "num_envs", "sac", "time_obs"))),
           "metrics.json": lambda: st.one_of(json_file(METRICS), nested_mutation(METRICS), mutated_values(METRICS, (
               "success_rate", "mean_contact_force", "mean_episode_reward", "time_to_first_success_s", "training",
               "wall_s", "eval_seed", "per_episode", "prior_eval", "paired_gain"))),
           CURVES_FILE: lambda: damaged_curves()}


def _valid_metrics(metrics: dict):
    for m in ("success_rate", "mean_contact_force", "mean_episode_reward", "time_to_first_success_s"):
        v = metrics.get(m)
        assert v is None or (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)), (m, v)


@pytest.mark.parametrize("part", sorted(DAMAGED))
@settings(FUZZ, max_examples=60)
@given(data=st.data())
def test_a_runs_files(report_py, seed_run, other_seed, tmp_path_factory, part, data):
    """load_run on a run directory with one file damaged: a valid run (its metrics finite numbers or null; its
    cell, tables, gain rows and curves formed), or one line naming that file."""
    run_dir = tmp_path_factory.mktemp("run") / "PegInsert_factory_4d_kgrl+lab" / "seed0"
    run_dir.parent.mkdir()
    shutil.copytree(seed_run, run_dir)
    (run_dir / part).write_bytes(data.draw(DAMAGED[part]()))
    check = _valid_run(report_py, run_dir, (other_seed,))

    def valid(loaded):
        _valid_metrics(loaded[1])
        check(loaded)

    refused_or_valid(lambda p: report_py.load_run(run_dir), run_dir / part, valid)


@FUZZ
@given(data=st.data())
def test_curves_jsonl(tmp_path_factory, data):
    """read_curves and results.plots.read_run: rows of finite numbers (or NaN for null), or one line naming the
    file and its line."""
    run_dir = tmp_path_factory.mktemp("curves")
    (run_dir / "config.json").write_text(json.dumps(CONFIG))
    (run_dir / CURVES_FILE).write_bytes(data.draw(damaged_curves()))

    def valid(rows):
        assert all(isinstance(r[k], (int, float)) and not isinstance(r[k], bool) for r in rows for k in CURVE_KEYS)
        assert all(math.isfinite(r["transitions"]) for r in rows)
        assert not any(math.isinf(r[k]) for r in rows for k in CURVE_KEYS)

    rows = refused_or_valid(lambda p: read_curves(p.parent), run_dir / CURVES_FILE)
    if rows is not None:
        valid(rows)
        read_run(run_dir)
    else:
        with pytest.raises(ValueError, match="line [0-9]+|not a readable"):
            read_run(run_dir)


def test_read_curves_names_the_line_and_what_is_wrong(tmp_path):
    good = json.dumps({"transitions": 8, "success_rate": 0.5})
    for line, message in (('{"transitions": 16, "success_rate": "high"}', "line 2 is not a curve row: success_rate is"),
                          ("[1, 2]", "line 2 is not a curve row: a JSON list, not an object"),
                          ('{"transitions": 16, "wall_s": NaN}', "line 2 is not a curve row (ValueError: bare NaN"),
                          ('{"transitions": 16, "wall_s": 1e999}', "wall_s is inf, not a finite number"),
                          ('{"success_rate": 0.5}', "line 2 is not a curve row: it has no transitions"),
                          ('{"transitions": 16, "wall_s": true}', "wall_s is True, not a number")):
        (tmp_path / CURVES_FILE).write_text(f"{good}\n{line}\n{good}\n")
        with pytest.raises(ValueError, match="^" + str(tmp_path / CURVES_FILE) + ": ") as e:
            read_curves(tmp_path)
        assert message in str(e.value), (line, str(e.value))
    (tmp_path / CURVES_FILE).write_bytes(f"{good}\n{good}\n".encode() + b'{"transitions": 1\xff}\n')
    with pytest.raises(ValueError, match="line 3 is not UTF-8 text"):
        read_curves(tmp_path)
    (tmp_path / CURVES_FILE).write_text(f"{good}\n{good}\n" + '{"transitions": 2')  # a kill mid-write: left out
    assert len(read_curves(tmp_path)) == 2


def test_a_curve_writer_writes_inf_as_null(tmp_path):
    CurveWriter(tmp_path).append(transitions=8, **{**CURVE, "peak_contact_force": math.inf})
    assert '"peak_contact_force": null' in (tmp_path / CURVES_FILE).read_text()
    assert math.isnan(read_curves(tmp_path)[0]["peak_contact_force"])


def test_read_run_refuses_a_config_without_what_the_curves_are_grouped_by(tmp_path):
    (tmp_path / "config.json").write_bytes(b'{"method": "sac", "seed": 0}')
    with pytest.raises(ValueError, match=f"^{tmp_path / 'config.json'} is damaged: it has no 'task'$"):
        read_run(tmp_path)
    (tmp_path / "config.json").write_bytes(b"\xff\xfe{}")
    with pytest.raises(ValueError, match=f"^{tmp_path / 'config.json'}: not a readable run's config.json"):
        read_run(tmp_path)


# ----------------------------------------------------------------------------- --from-stats: stats.json
PEG = {"task": "PegInsert", "env": "factory", "action_dim": 4}
STATS = {"prior_gain": [{**PEG, "method": "kgrl", "seed_ids": [0, 1, 2], "seed_gains": [0.25, None, 0.5],
                         "prior_success": 0.25},
                        {**PEG, "method": "kgrl+x", "seed_ids": [0, 1, 2], "seed_gains": [0.5, 0.0, 0.5],
                         "prior_success": 0.25}],
         "method_pairs": [{**PEG, "a": "sac", "b": "kgrl", "seeds": [0, 1], "seed_differences": [0.1, 0.2]}]}


@FUZZ
@given(data=st.data())
def test_an_earlier_reports_stats_json(report_py, tmp_path_factory, data):
    """read_stats, as --from-stats reads it: the seed statistics and their table are formed, or one line."""
    path = tmp_path_factory.mktemp("stats") / "stats.json"
    block = data.draw(st.sampled_from(("prior_gain", "method_pairs")))
    kind = data.draw(st.sampled_from(("file", "row")))
    if kind == "file":
        path.write_bytes(data.draw(json_file(STATS)))
    else:  # one row's fields removed or of another type
        stats = copy.deepcopy(STATS)
        stats[block][0] = _mutated_row(data, STATS[block][0])
        path.write_text(json.dumps(stats))

    def valid(_):
        rows = report_py.restat_rows([path], reps=2)
        report_py.restat_markdown(rows, [path])
        strict_json(rows)

    refused_or_valid(report_py.read_stats, path, valid)


def test_seed_statistics_of_one_nonzero_seed_difference():
    """scipy's exact Wilcoxon wants two nonzero seeds; with one, both sign patterns are as extreme (p = 1)."""
    from vkgrl_newton.results.seeds import over_seeds

    s = over_seeds([0.25, 0.0], reps=2)
    assert s["wilcoxon_p"] == 1.0 and s["wilcoxon_statistic"] == 0.0 and s["sign_p"] == 1.0


def _mutated_row(data, row: dict) -> dict:
    row = copy.deepcopy(row)
    key = data.draw(st.sampled_from(sorted(row)))
    if data.draw(st.booleans()):
        row.pop(key)
    elif isinstance(row[key], list) and row[key] and data.draw(st.booleans()):
        row[key][data.draw(st.integers(0, len(row[key]) - 1))] = data.draw(JSON)
    else:
        row[key] = data.draw(JSON)
    return row


# ----------------------------------------------------------------------------- the command line
def _report(*argv):
    return subprocess.run([sys.executable, "train/report.py", *map(str, argv)], cwd=ROOT, capture_output=True,
                          text=True, timeout=300)


def _refused(out, target: Path, *needles):
    assert out.returncode == 2, (out.returncode, out.stderr[-2000:])
    assert "Traceback" not in out.stderr, out.stderr[-2000:]
    last = out.stderr.strip().splitlines()[-1]
    assert last.startswith("report.py: error: ") and str(target) in last, last
    for n in needles:
        assert n in last, last


DAMAGES = {  # file -> (its damaged content, what the line says)
    "no method": ("config.json", json.dumps({k: v for k, v in CONFIG.items() if k != "method"}), "it has no 'method'"),
    "a metric that is no number": ("metrics.json", json.dumps({**METRICS, "success_rate": "high"}),
                                   "success_rate is 'high', not a number"),
    "bare NaN": ("metrics.json", json.dumps({**METRICS, "mean_contact_force": math.nan}), "bare NaN"),
    "a world outcome that is no number": ("metrics.json", json.dumps(
        {**METRICS, "per_episode": [{"world_success": [1.0, "x"]}, ROUNDS[1]]}), "per_episode[0].world_success[1]"),
    "a curve row that is no object": (CURVES_FILE, '{"transitions": 8}\n[1, 2]\n{"transitions": 16}\n',
                                      "line 2 is not a curve row"),
    "bad UTF-8 in the curves": (CURVES_FILE, b'{"transitions": 8}\n{"transitions": 16\xff}\n{"transitions": 24}\n',
                                "line 2 is not UTF-8 text"),
}


def test_report_py_refuses_a_sweep_with_a_damaged_run_in_one_line_and_writes_nothing(seed_run, tmp_path):
    """A sweep of good runs and one damaged run (each damage above; then the same in a report's copy of the
    runs under <report>/runs, read back): exit 2, one line naming the damaged file, no traceback, no --out."""
    report_py = load_script("report")
    for i, (name, (part, content, needle)) in enumerate(DAMAGES.items()):
        sweep = tmp_path / f"sweep{i}"
        for seed in range(2):
            config = {**CONFIG, "seed": seed}
            write_run(sweep / "PegInsert_factory_4d_kgrl+lab" / f"seed{seed}", config)
        damaged = sweep / "PegInsert_factory_4d_kgrl+lab" / "seed1" / part
        (damaged.write_bytes if isinstance(content, bytes) else damaged.write_text)(content)
        if i % 2:  # read back from a report's copy of the runs, the runs themselves gone
            report = tmp_path / f"report{i}"
            report.mkdir()
            report_py.archive_runs(report_py.find_runs([sweep]), report / "runs")
            shutil.rmtree(sweep)
            damaged = report / "runs" / "PegInsert_factory_4d_kgrl+lab" / "seed1" / part
            sweep = report
        out = tmp_path / f"out{i}"
        _refused(_report(sweep, "--out", out, "--reps", "10"), damaged, needle, "is damaged" if part != CURVES_FILE
                 else "restore it")
        assert not out.exists() and not list(tmp_path.glob(f".out{i}.partial-*")), name


def test_report_py_from_stats_refuses_a_damaged_stats_json_in_one_line(tmp_path):
    stats = tmp_path / "old" / "stats.json"
    stats.parent.mkdir()
    stats.write_text(json.dumps({"prior_gain": [{**STATS["prior_gain"][0], "seed_gains": [0.1, "x", 0.2]}]}))
    _refused(_report("--from-stats", stats.parent, "--out", tmp_path / "out"), stats,
             "prior_gain[0].seed_gains[1] is 'x', not a number")
    assert not (tmp_path / "out").exists()
