"""The house (docs/architecture.md): layers whose imports point down, no import circle, no project
import inside a function, one sensor stage with one storage-time rule."""

from __future__ import annotations

import ast
import subprocess
import tomllib
import sys
from pathlib import Path

import numpy as np
import pytest
from script_modules import load_script

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "mbcapture"


def test_imports_follow_the_layers_contract():
    """import-linter's layers contract of pyproject.toml: every import, function-local ones too,
    points down the layers."""
    exe = Path(sys.executable).with_name("lint-imports")
    proc = subprocess.run([str(exe), "--no-cache"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-2000:]
    contracts = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"]
    assert "0 broken" in proc.stdout and f"{len(contracts)} kept" in proc.stdout  # every contract ran


def _strongly_connected(edges: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module: scripts/house_metrics.py's, which prints them."""
    return load_script("house_metrics").circles(edges)


def test_no_import_circle_anywhere_in_the_package():
    """Between any modules, packages' insides included, counting imports under ``TYPE_CHECKING`` too (an
    annotation that points up is a circle all the same)."""
    import grimp

    graph = grimp.build_graph("mbcapture", exclude_type_checking_imports=False, cache_dir=None)
    edges = {m: set(graph.find_modules_directly_imported_by(m)) for m in graph.modules}
    assert _strongly_connected(edges) == []
    # the check itself finds a circle
    assert _strongly_connected({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def _function_local_project_imports(path: Path, root: Path = ROOT) -> list[str]:
    tree = ast.parse(path.read_text())
    found = []
    for fn in ast.walk(tree):
        if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            for node in ast.walk(fn):
                project = (
                    isinstance(node, ast.ImportFrom) and (node.level or (node.module or "").startswith("mbcapture"))
                ) or (isinstance(node, ast.Import) and any(a.name.startswith("mbcapture") for a in node.names))
                if project:
                    found.append(f"{path.relative_to(root)}:{node.lineno} in {fn.name}: {ast.unparse(node)}")
    return found


def test_no_project_import_inside_a_function():
    """Project modules are imported at the top of a module; only heavy third-party libraries
    (Mitsuba, matplotlib, OpenCV, Dask, colour, ...) load inside the functions that need them."""
    found = [hit for p in sorted(PACKAGE.rglob("*.py")) for hit in _function_local_project_imports(p)]
    assert found == []


def test_the_local_import_check_finds_one(tmp_path):
    (tmp_path / "m.py").write_text(
        "import numpy\n\ndef f():\n    from .x import y\n    import mbcapture.output.io\n    import os\n"
    )
    hits = _function_local_project_imports(tmp_path / "m.py", root=tmp_path)
    assert [h.split(": ", 1)[1] for h in hits] == ["from .x import y", "import mbcapture.output.io"]


@pytest.mark.render
def test_main_and_comparison_captures_share_one_sensor_stage_and_storage_rule():
    """The main capture (pipeline) and a comparison capture of the same timeline (simulate.capture_timeline,
    which bursts and videos use) give each bucket the same dark charge: dark current over its storage time
    (Timeline.storage_s: from its first slot to the read after the capture's last slot), and none for a
    bucket that never collects (bucket 2 here). Dark current 1e5 e-/s (~1200 e-, below the full well): each bucket's mean over 8x6x3
    samples has a standard error of sqrt(mean / 144); the means must agree within 6 of them."""
    from mbcapture import load_config, run_capture
    from mbcapture.capture.pipeline import prepare
    from mbcapture.render import Renderer
    from mbcapture.sensor import electrons_per_render_second, sensor_stage_hook
    from mbcapture.exposure.simulate import capture_timeline

    cfg = load_config(
        None,
        [
            "scene.name=flatfield",
            "render.width=8",
            "render.height=6",
            "render.spp=2",
            "capture.protocol=custom",
            "capture.schedule.slots=[{bucket: 1, duration_s: 0.001}, {bucket: 3, duration_s: 0.002}]",
            "capture.schedule.reads=[{buckets: [1]}, {buckets: [3]}]",
            "capture.periods=4",
            "app.name=hdr",
            "sensor.dark_current_e_per_s=1e5",
            "sensor.read_noise_e=0",
            "sensor.dsnu_e=0",
        ],
    )
    dark: list[np.ndarray] = []

    def hook(expected_e, simulate):
        dark.append(simulate(np.zeros_like(expected_e)).electrons)  # the same sensor with no light: dark charge only
        return simulate(expected_e)

    with sensor_stage_hook(hook):
        res = run_capture(cfg, progress=False)
        scene = prepare(cfg)[0]
        capture_timeline(
            res.timeline,
            scene,
            cfg,
            Renderer.from_config(scene, cfg),
            2,
            np.random.SeedSequence(9),
            electrons_per_render_second(cfg.sensor, cfg.render.variant),
        )
    storage_s = res.timeline.storage_s()
    assert res.timeline.n_buckets == 3 and storage_s[1] == 0.0 and storage_s[0] > 0 and storage_s[2] > 0
    main, comparison = dark
    assert main.shape == comparison.shape == (3, 6, 8, 3)
    n = main[0].size
    for k in range(3):
        expected = 1e5 * storage_s[k]
        for got in (main[k].mean(), comparison[k].mean()):
            assert abs(got - expected) <= 6 * np.sqrt(max(expected, 1.0) / n), (k, got, expected)
    assert np.all(main[1] == 0) and np.all(comparison[1] == 0)


#: Wings that are collections of peers (one module per application, figure family or algorithm family): their row
#: names each module instead of a row per module.
COLLECTIONS = ("apps", "figures", "reconstruct")


def _table_rows() -> dict[str, str]:
    """docs/architecture.md's table: each name of a row's first cell -> the row's text."""
    doc = (ROOT / "docs" / "architecture.md").read_text()
    return {
        cell.strip().strip("` ").rstrip("/"): line
        for line in doc.splitlines()
        if line.startswith("| `")
        for cell in line.split("|")[1].split(",")
    }


def test_docs_architecture_names_every_module_of_the_package():
    """docs/architecture.md is the record of the layout: every module of the package (``wing/module``, or
    ``module`` at the root) and every wing has a row in its table, every top-level place is in the wings
    contract, and the root holds few modules beside its wings."""
    import tomllib

    layers = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"][0]["layers"]
    in_contract = {m.strip().removeprefix("mbcapture.") for layer in layers for m in layer.split("|")}
    root_modules = {p.stem for p in PACKAGE.glob("*.py") if p.stem != "__init__"}
    wings = {p.parent.name for p in PACKAGE.glob("*/__init__.py")}
    assert (root_modules | wings) - in_contract == set(), "places outside the wings contract"
    assert len(root_modules) <= 12, sorted(root_modules)
    rows = _table_rows()
    modules = root_modules | wings
    for wing in wings:
        inside = {p.stem for p in (PACKAGE / wing).glob("*.py") if p.stem != "__init__"}
        if wing in COLLECTIONS:
            unnamed = {m for m in inside if f"`{m}`" not in rows.get(wing, "")}
            assert unnamed == set(), f"{wing}/'s row in docs/architecture.md does not name {sorted(unnamed)}"
        else:
            modules |= {f"{wing}/{m}" for m in inside}
    missing = modules - {"__main__"} - set(rows)
    assert missing == set(), f"modules without a row in docs/architecture.md: {sorted(missing)}"


def _imports(path: Path) -> list[tuple[str, list[str]]]:
    """(module, names) of every import of ``path``, function-local ones too (relative ones resolved)."""
    package = ".".join(path.relative_to(ROOT).with_suffix("").parts[:-1])
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found += [(a.name, []) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = package.split(".")[: len(package.split(".")) - node.level + 1] if node.level else []
            module = ".".join([*base, *([node.module] if node.module else [])])
            found.append((module, [a.name for a in node.names]))
    return found


def _package_files(*, but: tuple[str, ...] = ()) -> list[Path]:
    return [p for p in sorted(PACKAGE.rglob("*.py")) if not str(p.relative_to(PACKAGE)).startswith(but)]


def test_every_capture_reads_its_sensor_through_the_one_sensor_stage():
    """No module of a capture calls the pixel model (``sensor.simulate_reads``) itself: the main capture and every
    comparison capture go through ``exposure.simulate`` (sense, sense_frame, capture_timeline), which gives each
    bucket its storage time. Only the sensor's own studies (studies/, figures/) read a sensor without a capture."""
    capture_side = [
        p
        for p in _package_files(but=("sensor", "studies", "figures", "exposure/simulate.py"))
        if not p.name == "__init__.py" or p.parent != PACKAGE / "sensor"
    ]
    found = [
        f"{p.relative_to(ROOT)}: {m}" for p in capture_side for m, names in _imports(p) if "simulate_reads" in names
    ]
    assert found == []


def test_drawing_and_mitsuba_each_live_in_one_place():
    """matplotlib draws in output/plots.py and figures/ only (``matplotlib.path``'s geometry aside), Mitsuba and
    Dr.Jit are imported in render/ only."""
    drawing = [
        f"{p.relative_to(ROOT)}: {m}"
        for p in _package_files(but=("output/plots.py", "figures"))
        for m, _ in _imports(p)
        if m.split(".")[0] == "matplotlib" and m != "matplotlib.path"
    ]
    assert drawing == []
    mitsuba = [
        f"{p.relative_to(ROOT)}: {m}"
        for p in _package_files(but=("render",))
        for m, _ in _imports(p)
        if m.split(".")[0] in ("mitsuba", "drjit")
    ]
    assert mitsuba == []


def test_no_private_name_is_imported_across_modules():
    """A name another module needs is public: no ``from mbcapture.x import _name``."""
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.level or (node.module or "").startswith("mbcapture")):
                found += [
                    f"{path.relative_to(ROOT)}:{node.lineno}: {a.name}"
                    for a in node.names
                    if a.name.startswith("_") and not a.name.startswith("__")
                ]
    assert found == []


#: The most lines a module of the package, and a function, may have: a reader holds a unit in view.
MAX_MODULE_LINES = 800
MAX_FUNCTION_LINES = 100


def _long_units(root: Path) -> list[str]:
    found = []
    for path in sorted(root.rglob("*.py")):
        text = path.read_text()
        if text.count("\n") > MAX_MODULE_LINES:
            found.append(f"{path.relative_to(root)}: {text.count(chr(10))} lines")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                length = node.end_lineno - node.lineno + 1
                if length > MAX_FUNCTION_LINES:
                    found.append(f"{path.relative_to(root)}:{node.lineno} {node.name}: {length} lines")
    return found


def test_no_module_or_function_is_too_long_to_read(tmp_path):
    """No module over MAX_MODULE_LINES lines, no function (docstring included) over MAX_FUNCTION_LINES."""
    assert _long_units(PACKAGE) == []
    # the check itself finds both
    (tmp_path / "long.py").write_text("def f():\n" + "    x = 1\n" * MAX_FUNCTION_LINES + "\n" * MAX_MODULE_LINES)
    assert [h.split(":")[0] for h in _long_units(tmp_path)] == ["long.py", "long.py"]
