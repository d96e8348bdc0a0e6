"""Reports: a real tiny-scale reproduce-paper, its files, its numbers, and a browser."""
import re
import shutil

import matplotlib.image as mpimg
import numpy as np
import pandas as pd
import pytest

from mpe3d.cli import main
from mpe3d.harness.tracking.store import Tracker
from mpe3d.reports.load import published
from mpe3d.sweeps import paper_sweeps
from tests.helpers import SHARED, run_cli

TABLES = ["claims", "allmetrics", "allmetrics_seen2", "allmetricspix3d", "allmetricspix3d_seen2",
          "smart_init", "noise_distance", "noise_correspondence", "views", "points", "visibility",
          "raytrace_visible", "angle_band", "occlusion", "colmap", "colmap_tracks"]
FIGURES = ["smart_init", "noise_distance", "noise_correspondence", "views_runtime", "views_metrics",
           "points_runtime", "points_metrics", "visibility", "raytrace_visible", "angle_band"]


@pytest.fixture(scope="module")
def tiny_report(tmp_path_factory):
    """One real ``mpe3d reproduce-paper --scale tiny`` (about 130 small runs), then a rerun."""
    folder = tmp_path_factory.mktemp("reproduce")
    uri = f"sqlite:///{folder}/mlflow.db"
    first = run_cli("reproduce-paper", "--scale", "tiny", "--jobs", "2", "--out", "report",
                    "--tracking-uri", uri, "--quiet", cwd=folder)
    assert first.returncode == 0, first.stderr
    second = run_cli("reproduce-paper", "--scale", "tiny", "--out", "again", "--tracking-uri", uri,
                     "--quiet", cwd=folder)
    assert second.returncode == 0, second.stderr
    return folder, uri, first, second


@pytest.mark.slow  # a real sweep or server: the full suite runs it
def test_report_folder_holds_every_table_and_figure(tiny_report):
    folder, _, first, _ = tiny_report
    out = folder / "report"
    for name in TABLES:
        assert (out / "tables" / f"{name}.md").stat().st_size > 100, name
        tex = (out / "tables" / f"{name}.tex").read_text()
        assert "\\toprule" in tex and "\\bottomrule" in tex, name  # booktabs
    for name in FIGURES:
        assert (out / "figures" / f"{name}.pdf").read_bytes().startswith(b"%PDF"), name
        image = mpimg.imread(out / "figures" / f"{name}.png")
        assert image.shape[0] > 200 and image.shape[1] > 200, name
        assert image[..., :3].std() > 0.05, f"{name}.png looks blank"
    index = (out / "index.md").read_text()
    page = (out / "index.html").read_text()
    for name in FIGURES:
        assert f"figures/{name}.png" in index and f"figures/{name}.png" in page
    for name in TABLES:
        assert f"tables/{name}.md" in index
    assert re.search(r"Scale tiny; \d+ runs in 12 experiments: \d+ run now, 0 reused", index)
    assert "wall time for the runs" in index
    assert "wrote report/index.html" in first.stdout
    # Each parent run in MLflow carries its experiment's part of the report.
    from mlflow.tracking import MlflowClient
    client = MlflowClient(f"sqlite:///{folder}/mlflow.db")
    experiment = client.get_experiment_by_name("paper-views")
    (parent,) = [r for r in client.search_runs([experiment.experiment_id])
                 if "mlflow.parentRunId" not in r.data.tags]
    logged = {a.path for a in client.list_artifacts(parent.info.run_id, "summary/figures")}
    assert {"summary/figures/views_metrics.png", "summary/figures/views_runtime.png"} <= logged


@pytest.mark.slow  # a real sweep or server: the full suite runs it
def test_tables_hold_the_runs_numbers(tiny_report):
    folder, uri, _, _ = tiny_report
    runs = Tracker(uri, create=False).runs_frame("paper-views")
    runs = runs[runs["status"] == "FINISHED"]
    table = (folder / "report" / "tables" / "views.md").read_text()
    for (setting, k, solver), group in runs.groupby(["projections", "views", "solver.name"]):
        mean = group["cd_x100"].mean()
        assert f"{mean:.3g}" in table, (setting, k, solver, mean)
    allmetrics = (folder / "report" / "tables" / "allmetrics.md").read_text()
    paper = published("allmetrics")
    chair_cd = paper[(paper.category == "chair") & (paper.metric == "CD") & (paper.method == "PSGN")]
    assert f"{chair_cd.value.iloc[0]:.3g}" in allmetrics and "published, ShapeNet" in allmetrics


@pytest.mark.slow  # a real sweep or server: the full suite runs it
def test_rerun_reuses_every_run(tiny_report):
    folder, _, _, second = tiny_report
    index = (folder / "again" / "index.md").read_text()
    assert re.search(r"\d+ runs in 12 experiments: 0 run now, \d+ reused", index)
    assert sorted(p.name for p in (folder / "again" / "figures").iterdir()) == \
        sorted(p.name for p in (folder / "report" / "figures").iterdir())


@pytest.mark.slow  # a real sweep or server: the full suite runs it
def test_report_commands_and_their_errors(tiny_report, capsys):
    folder, uri, _, _ = tiny_report
    one = run_cli("report", "--experiment", "paper-angle-band", "--out", "one",
                  "--tracking-uri", uri, cwd=folder)
    assert one.returncode == 0, one.stderr
    assert (folder / "one" / "figures" / "angle_band.png").exists()
    sweep = [p for p in paper_sweeps() if p.name == "points.yaml"][0]
    assert main(["report", "--sweep", str(sweep), "--scale", "tiny", "--out", str(folder / "two"),
                 "--tracking-uri", uri]) == 0
    assert (folder / "two" / "tables" / "points.md").exists()
    capsys.readouterr()
    for args, message in [
        (["--experiment", "paper-angel-band"], "no experiment 'paper-angel-band'"),
        (["--sweep", "missing.yaml"], "cannot read sweep file missing.yaml"),
        (["--sweep", str(sweep), "--scale", "huge"], "has no scale 'huge'"),
    ]:
        assert main(["report", *args, "--out", str(folder / "x"), "--tracking-uri", uri]) == 2
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err and len(err.strip().splitlines()) == 1, err


@pytest.mark.skipif(not (SHARED / "reference").is_dir(), reason="../shared is not beside this checkout")
def test_published_numbers_ship_with_the_package():
    shipped = pd.concat([published("allmetrics"), published("allmetricspix3d")])
    source = pd.read_csv(SHARED / "reference" / "paper_tables.csv")
    assert len(shipped) == len(source) and np.allclose(shipped["value"], source["value"])


def _chromium():
    return shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.mark.skipif(not _chromium() or not shutil.which("chromedriver"),
                    reason="needs Debian's chromium and chromium-driver (.ci/run installs them)")
@pytest.mark.slow  # a real sweep or server: the full suite runs it
def test_index_html_loads_with_all_images_in_a_real_browser(tiny_report):
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By

    folder, _, _, _ = tiny_report
    options = webdriver.ChromeOptions()
    options.binary_location = _chromium()
    for flag in ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 "--allow-file-access-from-files", f"--user-data-dir={folder / 'chromium'}"):
        options.add_argument(flag)
    driver = webdriver.Chrome(service=Service(shutil.which("chromedriver")), options=options)
    try:
        driver.get((folder / "report" / "index.html").as_uri())
        images = driver.execute_script(
            "return Array.from(document.images).map(i => [i.getAttribute('src'), i.complete, i.naturalWidth])")
        title = driver.title
        # The turnable clouds: every canvas drawn, and a drag with the mouse turns one.
        canvases = driver.find_elements(By.CSS_SELECTOR, "canvas.mpe3d-cloud")
        drawn = [c.get_attribute("data-rendered") for c in canvases]
        driver.execute_script("arguments[0].scrollIntoView()", canvases[0])
        before = driver.execute_script("return arguments[0].toDataURL()", canvases[0])
        ActionChains(driver).move_to_element(canvases[0]).click_and_hold().move_by_offset(60, 25) \
            .release().perform()
        after = driver.execute_script("return arguments[0].toDataURL()", canvases[0])
        blank = driver.execute_script(
            "const c = document.createElement('canvas'); c.width = arguments[0].width;"
            "c.height = arguments[0].height; const x = c.getContext('2d'); x.fillStyle = '#fff';"
            "x.fillRect(0, 0, c.width, c.height); return c.toDataURL()", canvases[0])
        # The claims: one short line each, the test and the numbers folded beneath it.
        driver.set_window_size(1200, 1000)
        claims = driver.find_elements(By.CSS_SELECTOR, "figure.folded details")
        folded_heights = [c.size["height"] for c in claims]
        hidden = [c.find_element(By.TAG_NAME, "dl").is_displayed() for c in claims]
        driver.execute_script("arguments[0].scrollIntoView()", claims[0])
        claims[0].find_element(By.TAG_NAME, "summary").click()
        opened = claims[0].find_element(By.TAG_NAME, "dl")
        unfolded = (opened.is_displayed(), opened.text, claims[0].size["height"])
        driver.save_screenshot(str(folder / "claims.png"))
    finally:
        driver.quit()
    assert len(canvases) >= 10 and drawn == ["1"] * len(canvases)  # a few per experiment
    assert before != after and before != blank
    assert claims and not any(hidden)
    assert max(folded_heights) <= 70  # a line or two of text, not a wall
    assert unfolded[0] and "test" in unfolded[1] and unfolded[2] > folded_heights[0]
    assert title == "3DMPE, reproduced with mpe3d"
    assert sorted(src for src, _, _ in images) == sorted(f"figures/{n}.png" for n in FIGURES)
    broken = [src for src, complete, width in images if not complete or width == 0]
    assert not broken, broken


def test_runs_logged_before_a_key_existed_read_as_its_default():
    from mpe3d.reports.load import runs as load_runs

    class Store:  # what runs_frame returns for runs logged before view_layout and min_views
        def runs_frame(self, experiment):
            return pd.DataFrame({"status": ["FINISHED"] * 2, "config_hash": ["a", "b"],
                                 "solver.name": ["sgd", "refine"],
                                 "visibility.min_views": [np.nan, 2.0]})

    frame = load_runs(Store(), "old")
    assert list(frame["visibility.min_views"]) == [0, 2] and set(frame["view_layout"]) == {"band"}
    assert list(frame["method"]) == ["3DMPE (paper)", "ours (refine)"]
    assert list(load_runs(Store(), "old", hashes=["b"])["config_hash"]) == ["b"]


def test_a_report_says_which_code_made_its_numbers(tmp_path):
    from mpe3d.reports import paper

    def section(codes):
        frame = pd.DataFrame({"status": ["FINISHED"] * len(codes), "config_hash": list("abcd")[:len(codes)],
                              "code": codes, "error": "", "solver.name": "sgd", "method": "3DMPE (paper)",
                              "views": range(3, 3 + len(codes)), "cd_x100": 1.0, "emd_x100": 2.0,
                              "roa": 0.1, "runtime_s": 0.5})
        return paper.Section("mine", frame, varying=("views",), code="0.1.0/aaaa")

    one = paper.write(tmp_path / "one", [section(["0.1.0/aaaa"] * 2)], "one")
    text = (one.out / "index.md").read_text()
    assert "Computed by code 0.1.0/aaaa (this code): 2 run(s)." in text and "Mixes runs" not in text
    mixed = paper.write(tmp_path / "mixed", [section(["0.1.0/aaaa", "0.0.9/bbbb", "0.0.9/bbbb"])], "m")
    text = (mixed.out / "index.md").read_text()
    assert "computed by 2 different versions of the code (0.0.9/bbbb: 2 run(s), " \
           "0.1.0/aaaa (this code): 1 run(s))" in text
    table = (mixed.out / "tables" / "summary.md").read_text()
    assert table.startswith("One row per setting and solver") and "Mixes runs of 2 code versions" in table


def test_a_sweep_without_roa_gets_its_summary_and_figures(tmp_path):
    """COLMAP's points have no correspondences, so a sweep of colmap runs alone
    has no ROA column: its summary shows the metrics it has (it raised a
    KeyError, and the sweep's summary was lost)."""
    from mpe3d.reports import paper

    frame = pd.DataFrame({"status": "FINISHED", "config_hash": list("abcd"), "code": "0.1.0/aaaa",
                          "error": "", "solver.name": "sgd", "method": "COLMAP",
                          "images.count": [25, 50, 100, 250], "cd_x100": [5.9, 3.9, 3.5, 3.4],
                          "emd_x100": [8.2, 6.5, 6.5, 5.9], "runtime_s": [4.4, 6.8, 12.4, 55.4]})
    done = paper.write(tmp_path, [paper.Section("colmap-only", frame, varying=("images.count",),
                                                code="0.1.0/aaaa")], "colmap-only")
    table = (done.out / "tables" / "summary.md").read_text()
    assert "CD mean" in table and "EMD mean" in table and "ROA" not in table and "55.4" in table
    figures = {p.stem for p in (done.out / "figures").glob("*.png")}
    assert {"cd_x100_vs_images_count", "runtime_s_vs_images_count"} <= figures
    assert not any("roa" in name for name in figures)
