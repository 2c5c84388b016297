"""Issue 42: the yard's paint commissioned from one picture of a sample (`cellctl calibrate paint`), a
following scan that uses it, samples that must be refused, the look of a scene named in its reference,
and the appearance bench's cases. Real twin pictures and scans.

Tests of: planners.paint_calibration, cellctl.scan.paint_sample, cellctl.commissioning.paint, cellctl.config_files,
sim.scenes.sample, cellctl.bench.appearance."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from skimage.color import deltaE_cie76, rgb2lab

from cellctl.bench.appearance import cases, drawn_cases, paint_from_metal, true_delta_e, verdict
from cellctl.cli import main
from cellctl.config import cell_planners_config, load_cell_config
from cellctl.scan.job import ScanError
from cellctl.scan.run import run_job
from cellctl.scan.spec import JobSpec
from configs import CONFIG_DIR
from planners.config import ConfigError
from sim.appearance import FINISHES, LIGHTS, PAINTS
from sim.scenes import SCENE_NAMES, SceneError, load_scene
from sim.scenes.scrap import write_scene_file

DATA = Path(__file__).parent / "data" / "scrap"


def _cell(tmp_path: Path) -> Path:
    """A copy of the sim cell's config in tmp_path (calibrating points it at the paint file)."""
    doc = yaml.safe_load((CONFIG_DIR / "cell.sim.yaml").read_text())
    doc["planners_config"] = str(CONFIG_DIR / doc.get("planners_config", "planners.yaml"))
    doc["runs_dir"] = str(tmp_path / "runs")
    path = tmp_path / "cell.yaml"
    path.write_text("# the test's cell\n" + yaml.safe_dump(doc))
    return path


def _lab(rgb) -> np.ndarray:
    return rgb2lab(np.asarray(rgb, dtype=np.float64).reshape(1, 1, 3)).reshape(3)


def _pink_box(tmp_path: Path) -> Path:
    """The issue's red-rust box in red rust, sprayed pink."""
    doc = yaml.safe_load((DATA / "red-rust-box.yaml").read_text())
    doc.pop("colors", None)
    doc["name"] = "pink_rust_box"
    doc["mesh"] = str(DATA / doc["mesh"])
    doc["appearance"] = {"finish": "rust_red", "paint": "pink", "light": "normal", "seed": 3}
    path = tmp_path / "pink-box.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def test_pink_on_rust_is_commissioned_and_a_following_scan_uses_it(tmp_path, capsys):
    cell = _cell(tmp_path)
    scene = str(_pink_box(tmp_path))
    cfg0, _ = load_cell_config(cell)
    with pytest.raises(ScanError, match="paint_not_separable"):  # red is commissioned: no red line on this piece
        run_job(JobSpec(cfg0, cell, scene, "gnbv", profile="initial_view", noise=False, out=str(tmp_path)))

    assert main(["calibrate", "paint", "--config", str(cell), "--name", "pink", "--finish", "rust_red"]) == 0
    written = yaml.safe_load((tmp_path / "paint.yaml").read_text())
    assert written["paint"]["name"] == "pink"
    assert float(deltaE_cie76(written["paint"]["lab_mean"], _lab(PAINTS["pink"]))) < 5  # the sample's pink, as lit
    assert written["delta_e"] >= 15
    assert (tmp_path / "paint_sample.png").is_file()
    assert "paint_file: paint.yaml" in cell.read_text() and list(tmp_path.glob("cell.yaml.*.bak"))
    assert "# the test's cell" in cell.read_text()  # the config's own text is kept

    cfg, _ = load_cell_config(cell)
    assert cfg.paint_file == "paint.yaml"
    pcfg = cell_planners_config(cfg, cell)
    assert pcfg.paint.name == "pink" and pcfg.paint.min_delta_e == 15.0  # colour from the file, limits from planners
    res, run_dir = run_job(JobSpec(cfg, cell, scene, "gnbv", noise=False, out=str(tmp_path), max_steps=3, cut=False))
    assert res.paint.ok and res.terminated_by != "paint_not_separable", res.paint
    assert res.coverage_percent > 50
    assert paint_from_metal(run_dir, load_scene(scene)) <= 0.02


def test_a_sample_without_paint_is_refused_and_nothing_written(tmp_path, capsys):
    cell = _cell(tmp_path)
    text = cell.read_text()
    assert main(["calibrate", "paint", "--config", str(cell), "--name", "pink", "--finish", "rust_patchy",
                 "--no-paint"]) == 1
    assert "no paint in the sample" in capsys.readouterr().err
    assert not (tmp_path / "paint.yaml").exists() and cell.read_text() == text
    assert (tmp_path / "paint_sample.png").is_file()  # the picture shows the operator what was seen


def test_paint_that_cannot_be_told_from_its_metal_is_refused(tmp_path, capsys):
    cell = _cell(tmp_path)
    assert main(["calibrate", "paint", "--config", str(cell), "--name", "white", "--finish", "galvanized"]) == 1
    err = capsys.readouterr().err
    assert "cannot be told from this metal" in err or "has the paint's colour" in err
    assert not (tmp_path / "paint.yaml").exists()


def test_bad_paint_files_are_refused_with_the_way_out(tmp_path):
    cell = _cell(tmp_path)
    cell.write_text(cell.read_text() + "paint_file: paint.yaml\n")
    cfg, _ = load_cell_config(cell)
    with pytest.raises(ConfigError, match="calibrate paint"):
        cell_planners_config(cfg, cell)
    (tmp_path / "paint.yaml").write_text("paint: {name: x, lab_mean: [50, 0, 0], min_delta_e: 2}\n")
    with pytest.raises(ConfigError, match="min_delta_e not read from a paint file"):
        cell_planners_config(cfg, cell)
    (tmp_path / "paint.yaml").write_text("paint: {name: x, lab_cov: [[1, 2, 0], [0, 1, 0], [0, 0, 1]]}\n")
    with pytest.raises(ConfigError, match="positive-definite"):
        cell_planners_config(cfg, cell)


def test_a_white_line_is_never_the_grey_table(tmp_path):
    """White paint passes the grey floor's colour: what the scan takes as paint is on the piece only
    (before, 98 % of an I-beam's drawing cloud was the table)."""
    cell = _cell(tmp_path)
    assert main(["calibrate", "paint", "--config", str(cell), "--name", "white", "--finish", "rust_red"]) == 0
    cfg, _ = load_cell_config(cell)
    scene = "i_beam@rust_red,white,normal,3"
    res, run_dir = run_job(JobSpec(cfg, cell, scene, "gnbv", profile="initial_view", noise=False, out=str(tmp_path)))
    assert res.paint.ok
    assert paint_from_metal(run_dir, load_scene(scene)) <= 0.02


def test_a_scene_reference_names_its_look(tmp_path):
    s = load_scene("t_piece@rust_brown,orange,warm,4")
    assert (s.appearance.finish, s.appearance.paint, s.appearance.light, s.appearance.seed) == \
        ("rust_brown", "orange", "warm", 4)
    assert load_scene("t_piece").appearance is None
    a, b = load_scene("scrap:0:3@drawn").appearance, load_scene("scrap:0:3@drawn").appearance
    assert a == b and a.finish in FINISHES  # drawn from its own seeded stream
    assert load_scene("scrap:0:3").drawing_polylines[0].tolist() == load_scene("scrap:0:3@drawn").drawing_polylines[0].tolist()
    with pytest.raises(SceneError, match="unknown light"):
        load_scene("t_piece@rust_red,red,noon")
    path = write_scene_file("scrap:0:3@rust_dark,green,dim,2", tmp_path)
    assert load_scene(str(path)).appearance.paint == "green"


def test_the_appearance_bench_covers_the_set_and_knows_separable_from_not():
    shapes = list(SCENE_NAMES)
    cs = cases(shapes, list(FINISHES), list(PAINTS), list(LIGHTS))
    textured = [c for c in cs if not c["reference"]]
    assert len(textured) == len(FINISHES) * len(PAINTS)
    assert {(c["finish"], c["paint"]) for c in textured} == {(f, p) for f in FINISHES for p in PAINTS}
    assert {c["shape"] for c in textured} == set(shapes) and {c["light"] for c in textured} == set(LIGHTS)
    assert sum(FINISHES[f].rust for f in FINISHES) >= 3 and len(PAINTS) >= 5 and len(LIGHTS) >= 3
    assert true_delta_e("grey_steel", "red", "normal") > 60
    assert true_delta_e("galvanized", "white", "dim") < 15  # white on zinc in dim light: no line to see
    assert true_delta_e("rust_red", "red", "shadow") < true_delta_e("rust_red", "red", "normal")
    # white paint turned from the lamp is grey steel's colour: apart when lit alike, alike when not
    assert true_delta_e("grey_steel", "white", "normal") > 40 > 15 > true_delta_e("grey_steel", "white", "normal",
                                                                                    shaded=True)
    assert len([c for c in cs if c["reference"]]) >= 2 * len(shapes)
    (g,) = drawn_cases(["scrap:0:5"])  # a generated piece in the look its generator draws
    a = load_scene(g["ref"]).appearance
    assert g["ref"] == "scrap:0:5@drawn" and (g["finish"], g["paint"], g["light"]) == (a.finish, a.paint, a.light)
    refused = dict(true_delta_e=10.0, terminated_by="paint_not_separable", views=0, cuts=0)
    assert verdict(refused) == "refused"
    assert verdict({**refused, "true_delta_e": 30.0}) == "refused, separable"
    done = dict(true_delta_e=30.0, terminated_by="frontier", views=4, cuts=2, coverage=99.0, path_max_mm=4.0,
                from_metal=0.001)
    assert verdict(done) == "ok"
    assert verdict({**done, "path_max_mm": 12.0}) == "path"
    assert verdict({**done, "path_max_mm": 12.0}, reference_path_mm=11.5) == "ok"  # as on grey steel
    assert verdict({**done, "from_metal": 0.3, "coverage": 90.0}) == "coverage + from metal"
    assert verdict({**done, "true_delta_e": 10.0}) == "not refused"


@pytest.mark.timeout(600)
def test_the_paint_is_commissioned_through_the_job_api_and_the_next_job_uses_it(tmp_path):
    """The tablet's way: `cell/<id>/paint/commission` over Zenoh on loopback, on a running service; a
    sample without paint is refused with the cell's paint unchanged; the next job finds the pink line."""
    from cellctl.service.api import CommissionPaintRequest
    from cellctl.service.client import CellError
    from cellctl.service.loopback import ServiceProcess

    svc = ServiceProcess(tmp_path / "cell", scene_dirs=[str(tmp_path)]).start()
    try:
        with svc.client(timeout_s=60.0) as c:
            assert c.paint().paint.name == "red" and c.paint().paint_file is None
            bare = c.commission_paint(CommissionPaintRequest(name="pink", twin_finish="rust_red", twin_no_paint=True))
            assert not bare.ok and "no paint in the sample" in bare.reason and bare.picture_png_base64
            assert c.paint().paint.name == "red"
            with pytest.raises(CellError) as e:
                c.commission_paint({"name": "pink", "twin_paint": "fuchsia"})
            assert e.value.code == "invalid_request" and "fuchsia" in e.value.message
            done = c.commission_paint({"name": "pink", "twin_finish": "rust_red", "requested_by": "ana"})
            assert done.ok and done.paint.name == "pink" and done.delta_e >= 15
            assert c.paint().paint.name == "pink" and c.paint().paint_file.endswith("paint.yaml")
            assert "paint_file: paint.yaml" in svc.config.read_text()  # a restart keeps it
            job = c.submit({"scene": str(_pink_box(tmp_path)), "max_steps": 2})
            with pytest.raises(CellError) as e:  # the camera is the job's now
                c.commission_paint({"name": "red"})
            assert e.value.code == "cell_busy"
            rec = c.wait(job.job_id, timeout_s=400)
            assert rec.state == "done", rec.error
            assert rec.result.paint.ok
    finally:
        svc.stop()


@pytest.mark.xfail(strict=True, reason="known (issue 42): on faces turned from the lamp the paint's shaded colour "
                   "reaches the metal's: fixes tried at 711f95a (the paint's spread capped, no double shading, near "
                   "black never paint) passed these two but let white on grey steel and orange on patchy rust take "
                   "19-73 % of their paint clouds from the metal over the appearance bench; reverted")
@pytest.mark.parametrize("ref, paint", [("t_piece@rust_patchy,yellow,dim,67", "yellow"),
                                        ("i_beam@rust_red,white,shadow,80", "white")])
def test_paint_on_faces_turned_from_the_lamp_never_takes_the_metal(tmp_path, ref, paint):
    """Found by `cellctl bench --appearance` (c78d5a3): yellow in dim light shaded twice over matched dark rust
    (17 % of the T-piece's paint cloud, a cut 146 mm off the line), white with a fitted spread that held
    the shading matched rust in a shadow (43 % of the I-beam's). Each view's paint stays on the line."""
    cell = _cell(tmp_path)
    assert main(["calibrate", "paint", "--config", str(cell), "--name", paint, "--finish", "rust_patchy"]) == 0
    cfg, _ = load_cell_config(cell)
    res, run_dir = run_job(JobSpec(cfg, cell, ref, "gnbv", seed=0, out=str(tmp_path), max_steps=5, cut=False))
    assert res.paint.ok
    assert paint_from_metal(run_dir, load_scene(ref)) <= 0.02
