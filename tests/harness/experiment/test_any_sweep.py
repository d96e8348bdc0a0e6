"""A user's own sweep, end to end: overrides on the command line, a grid that
mixes solvers with different options, its report, and what MLflow shows."""
import matplotlib.image as mpimg
import pytest
from mlflow.tracking import MlflowClient

from mpe3d import load_sweep
from mpe3d.cli import main
from tests.helpers import run_cli

MIXED = """\
name: mixed
base: {shape: torus, points: 40, views: 3, projections: variable, visibility: {mode: exact, k: 2}}
grid:
  solver:
    - {name: baseline, method: classical}
    - {name: sgd, max_iter: 30}
    - {name: sgd, max_iter: 30, step: bb}
    - refine
"""


@pytest.fixture(scope="module")
def mixed(tmp_path_factory):
    folder = tmp_path_factory.mktemp("mixed")
    path = folder / "mixed.yaml"
    path.write_text(MIXED)
    uri = f"sqlite:///{folder}/mlflow.db"
    # points=48 and a grid axis over views, from the command line.
    # Overrides anywhere among the options, as Hydra users type them.
    ran = run_cli("sweep", str(path), "--jobs", "2", "points=48", "--tracking-uri", uri,
                  "grid.views=[3, 4]", cwd=folder)
    assert ran.returncode == 0, ran.stderr
    report = run_cli("report", "--sweep", str(path), "points=48", "grid.views=[3, 4]", "--out", "rep",
                     "--tracking-uri", uri, cwd=folder)
    return folder, path, uri, ran, report


def test_overrides_hash_as_if_written_in_the_file(tmp_path, capsys):
    path = tmp_path / "mixed.yaml"
    path.write_text(MIXED)
    written = tmp_path / "written.yaml"
    written.write_text(MIXED.replace("points: 40", "points: 48") + "  views: [3, 4]\n")
    by_hand = {c.hash() for c in load_sweep(written).runs}
    overridden = load_sweep(path, overrides=["points=48", "grid.views=[3, 4]"])
    assert {c.hash() for c in overridden.runs} == by_hand and len(by_hand) == 8
    for bad, message in [("points=abc", "points: expected an integer, got 'abc' at the command line"),
                         ("grid.views=4", "grid.views: expected a list like [a, b]"),
                         ("solver=sgd", "solver varies in the sweep"),
                         ("pionts=3", "unknown key 'pionts' at the command line (pionts=3) (did you "
                                      "mean 'points'?)")]:
        assert main(["sweep", str(path), bad, "--dry-run"]) == 2
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) == 1, err


def test_overrides_go_anywhere_on_sweep_and_reproduce_paper(tmp_path, capsys):
    path = tmp_path / "mixed.yaml"
    path.write_text(MIXED)
    assert main(["sweep", str(path), "--quiet", "points=70", "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "4 runs in all" in out
    assert {c.flat()["points"] for c in load_sweep(path, overrides=["points=70"]).runs} == {70}
    assert main(["sweep", "--dry-run", str(path), "--scale", "full", "grid.views=[3, 4]"]) == 0
    assert "8 runs in all" in capsys.readouterr().out
    # reproduce-paper checks its overrides on every experiment before any store is opened.
    assert main(["reproduce-paper", "--scale", "tiny", "pionts=3", "--quiet",
                 "--tracking-uri", f"sqlite:///{tmp_path}/never.db"]) == 2
    err = capsys.readouterr().err
    assert "unknown key 'pionts'" in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "never.db").exists()


@pytest.mark.slow  # a real sweep or server: the full suite runs it
def test_a_mixed_solver_report_has_a_row_per_setting_and_solver_and_its_figures(mixed):
    folder, _, _, _, report = mixed
    assert report.returncode == 0, report.stderr
    table = (folder / "rep" / "tables" / "summary.md").read_text()
    rows = [line for line in table.splitlines() if line.startswith("| ") and "---" not in line][1:]
    # 2 view counts × 4 solver variants (sgd twice: two step rules).
    assert len(rows) == 8
    assert sum("3DMPE (paper)" in r for r in rows) == 4 and sum("ours (refine)" in r for r in rows) == 2
    figures = sorted(p.stem for p in (folder / "rep" / "figures").glob("*.png"))
    assert figures == sorted(f"{m}_vs_{x}" for m in ("cd_x100", "emd_x100", "roa", "runtime_s")
                             for x in ("views",))
    for name in figures:
        image = mpimg.imread(folder / "rep" / "figures" / f"{name}.png")
        assert image[..., :3].std() > 0.05, f"{name}.png looks blank"
    page = (folder / "rep" / "index.html").read_text()
    assert page.count("class='mpe3d-cloud'") == 3 and (folder / "rep" / "viewer.js").is_file()
    assert "cdn" not in page.lower() and "http" not in (folder / "rep" / "viewer.js").read_text()


@pytest.mark.slow  # a real sweep or server: the full suite runs it
def test_mlflow_shows_pictures_and_names_runs_by_what_varies(mixed):
    _, _, uri, _, _ = mixed
    client = MlflowClient(uri)
    experiment = client.get_experiment_by_name("mixed")
    runs = client.search_runs([experiment.experiment_id])
    parents = [r for r in runs if "mlflow.parentRunId" not in r.data.tags]
    kids = [r for r in runs if "mlflow.parentRunId" in r.data.tags]
    assert len(parents) == 1 and len(kids) == 8
    for run in kids:
        name = run.data.tags["mlflow.runName"]
        assert "None" not in name and name.startswith("views=") and "solver.name=" in name, name
        assert {a.path for a in client.list_artifacts(run.info.run_id)} >= {"comparison.png"}
    assert any("solver.step=bb" in r.data.tags["mlflow.runName"] for r in kids)
    assert not any("max_iter" in r.data.tags["mlflow.runName"] for r in kids)  # same within sgd
    summary = {a.path for a in client.list_artifacts(parents[0].info.run_id, "summary")}
    assert {"summary/index.html", "summary/tables", "summary/figures"} <= summary


@pytest.mark.slow  # a real sweep or server: the full suite runs it
def test_a_report_without_rows_fails_and_writes_nothing(mixed, tmp_path, capsys):
    folder, path, uri, _, _ = mixed
    # The same sweep at other sizes was never run: nothing to report.
    code = main(["report", "--sweep", str(path), "points=64", "--out", str(tmp_path / "empty"),
                 "--tracking-uri", uri])
    err = capsys.readouterr().err
    assert code == 1 and "no finished runs of sweep" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "empty").exists()
