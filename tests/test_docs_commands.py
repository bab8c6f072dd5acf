"""Every command that README.md and docs/*.md show works as shown (issue 15).

* Fenced ``sh``/``bash``/``shell``/``console`` blocks are run, one command per line, from a scratch
  copy of the repository with ``$MBCAPTURE_SET`` making every capture tiny (16x12 px, 1 spp):
  ``mbcapture ...`` in this process (``cli.main``), ``make <target>`` as its Makefile recipe, a
  ``. file`` checks the file, anything else goes to bash. Fenced ``python`` blocks are executed.
  A command that cannot run here is in ``NOT_RUN`` with the reason and the form run instead.
* Inline code that names a command (``mbcapture``, ``python``, ``pytest``, ``make``, ``--set``) is
  checked without running: the subcommand, script, module, test file or make target exists, each
  ``--option`` it shows is one the program has, and a ``--set KEY=VALUE`` loads on the default config
  (configs/metronome_hdr.yaml). Synopses (``[--out DIR]``, ``CONFIG``) are checked the same way.

A new command in a fenced block needs nothing here: it runs at the tiny size automatically.
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
DEFAULT_CONFIG = ROOT / "configs" / "metronome_hdr.yaml"
TINY = "render.width=16 render.height=12 render.spp=1 render.max_motion_px=4 render.min_strata=1"
SHELL_BLOCKS = {"sh", "bash", "shell", "console"}

#: Commands shown that are not run as shown: the reason, and what runs instead (None: nothing).
NOT_RUN = {
    "make test": ("it is this test suite", None),
    "make setup": ("installs system packages and the .venv these tests run in", None),
    "mbcapture converge configs/metronome_hdr.yaml --quick": (
        "its --quick ladders are ~40 renders and a 64-spp reference: 18 s even at 16x12",
        "mbcapture converge configs/metronome_hdr.yaml --quick --spp 1,2 --naive-spp 1 --ref-spp 4 "
        "--set capture.periods=2",
    ),
    "mbcapture characterize metronome_hdr": (
        "a full datasheet, 504 frames of 128x128 pixels drawn exactly: 20 s of the suite "
        "(tests/test_characterize.py checks the command's datasheet at 48x40)",
        "mbcapture characterize metronome_hdr --size 32x32 --steps 20 --dark-steps 3 --frames 2",
    ),
    "mbcapture characterize metronome_hdr --set sensor.preset=global_shutter_cmos --out out/sheet_gs": (
        "a full datasheet of another preset: 7 s",
        "mbcapture characterize metronome_hdr --set sensor.preset=global_shutter_cmos --out out/sheet_gs --size 32x32 "
        "--steps 20 --dark-steps 3 --frames 2",
    ),
    # docs/design.md: a search is dozens of captures (or hundreds of analytic SNRs) even at 16x12; a short one runs
    "mbcapture design hdr_4bucket --out out/design_hdr_4bucket": (
        "24 designs x 3 seeds and the grid: a minute at 16x12",
        "mbcapture design hdr_4bucket --evaluations 2 --seeds 1 --out out/design_hdr_4bucket",
    ),
    "mbcapture design noise_optimal_sequential": (
        "300 analytic designs and the grid: 40 s",
        "mbcapture design noise_optimal_sequential --evaluations 6",
    ),
    "mbcapture design flash_no_flash --set render.width=160 --set render.height=128 --evaluations 60 --seeds 4": (
        "60 designs x 4 seeds",
        "mbcapture design flash_no_flash --set render.width=160 --set render.height=128 --evaluations 2 --seeds 1",
    ),
    # docs/tof.md: the designs' sweep is 16 captures, 100 s even at 16x12 (tests/test_tof.py checks how its points
    # share renders; the README's table is its output at 640x480)
    "mbcapture sweep tof_designs --out out/tof_designs": (
        "16 captures of up to 13 ms each: 100 s at 16x12",
        "mbcapture run tof_4tap --set capture.protocol=tof_1tap --set sensor.bucket_count=1 --out out/tof_1tap",
    ),
    # docs/tof.md: the benchmark renders 640x480-sized passes whatever MBCAPTURE_SET says
    "python scripts/benchmark_tof.py": (
        "renders at 320x240, 16 spp, three times per case",
        "python scripts/benchmark_tof.py --width 32 --height 24 --spp 1 --repeats 1",
    ),
    # docs/mutation.md: a mutation run is hours of CPU (every mutant runs its tests), and the report
    # and `mutmut show` read what a run left in mutants/
    "scripts/mutation.sh": ("a full mutation run: hours on 2 cores", None),
    "scripts/mutation.sh 'mbcapture.sensor.readout.*'": ("the readout's mutants: tens of minutes", None),
    ".venv/bin/mutmut show mbcapture.reconstruct.hdr.x__debevec__mutmut_26": ("reads a mutation run's mutants/", None),
    ".venv/bin/python scripts/mutation_report.py --survivors": ("reads a mutation run's mutants/", None),
}


# ----------------------------------------------------------------------------- extraction
def fenced_commands() -> list[tuple[str, int, str, str]]:
    """(file, line, language, command or code) of every fenced shell line and python block."""
    out = []
    for path in DOCS:
        text = path.read_text()
        for m in re.finditer(r"^```(\w*)[^\n]*\n(.*?)^```", text, re.S | re.M):
            lang, body = m.group(1).lower(), m.group(2)
            line0 = text[: m.start()].count("\n") + 2
            if lang == "python":
                out.append((path.name, line0, "python", body))
            elif lang in SHELL_BLOCKS:
                for i, line in enumerate(body.replace("\\\n", " ").splitlines()):
                    words = shlex.split(line, comments=True)
                    if words:
                        out.append((path.name, line0 + i, "sh", shlex.join(words)))
    return out


def inline_commands() -> list[tuple[str, int, str]]:
    """(file, line, text) of every inline code span that names a command with arguments."""
    out = []
    for path in DOCS:
        text = re.sub(r"^```.*?^```", lambda m: "\n" * m.group(0).count("\n"), path.read_text(), flags=re.S | re.M)
        for i, line in enumerate(text.splitlines(), 1):
            for span in re.findall(r"(?<!`)`([^`\n]+)`(?!`)", line):
                words = span.split()
                if len(words) >= 2 and words[0] in (
                    "mbcapture",
                    "python",
                    "pytest",
                    ".venv/bin/pytest",
                    "make",
                    "--set",
                ):
                    out.append((path.name, i, span))
    return out


FENCED = fenced_commands()
INLINE = inline_commands()


def unique_commands(found: list[tuple[str, int, str, str]]) -> list[tuple[str, str, str]]:
    """One run per distinct command or block, with every place that shows it ('README.md:44 +
    characterize.md:6'): a command shown twice does the same thing twice (the workspace is shared)."""
    places: dict[tuple[str, str], list[str]] = {}
    for where, line, lang, cmd in found:
        places.setdefault((lang, cmd), []).append(f"{where}:{line}")
    return [(" + ".join(at), lang, cmd) for (lang, cmd), at in places.items()]


RUNS = unique_commands(FENCED)


# ----------------------------------------------------------------------------- running
@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    """A scratch copy of the repository (big folders linked, the rest copied, so that a command
    that writes, e.g. into README.md or out/, cannot touch the real one)."""
    ws = tmp_path_factory.mktemp("docs-commands")
    for entry in ROOT.iterdir():
        if entry.name in ("out", ".git") or entry.name.startswith((".pytest", ".hypothesis")):
            continue
        if entry.name in (".venv", "mbcapture", "scenes", "tests") or entry.name.endswith(".egg-info"):
            (ws / entry.name).symlink_to(entry)
        elif entry.is_dir():
            shutil.copytree(entry, ws / entry.name, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy2(entry, ws / entry.name)
    return ws


def make_recipe(target: str, makefile: Path) -> list[str]:
    """The commands ``make target`` runs: its prerequisites' recipes, then its own."""
    text = makefile.read_text()
    m = re.search(rf"^{re.escape(target)}:([^\n]*)\n((?:\t[^\n]*\n?)*)", text, re.M)
    assert m, f"Makefile has no target {target!r}"
    cmds = []
    for dep in m.group(1).split():
        cmds += [f"make {dep}"] if f"make {dep}" in NOT_RUN else make_recipe(dep, makefile)
    return cmds + [line.strip() for line in m.group(2).splitlines() if line.strip()]


def run_command(cmd: str, ws: Path, capsys) -> None:
    from mbcapture.cli import main

    if cmd in NOT_RUN:
        reason, instead = NOT_RUN[cmd]
        if instead:
            run_command(instead, ws, capsys)
        return
    words = shlex.split(cmd)
    if words[0] in (".", "source"):
        assert (ws / words[1]).exists(), f"{cmd}: {words[1]} does not exist"
    elif words[0] == "make":
        for step in make_recipe(words[1], ws / "Makefile"):
            run_command(step, ws, capsys)
    elif words[0] in ("mbcapture", ".venv/bin/mbcapture"):
        try:
            rc = main(words[1:])
        except SystemExit as exc:  # --version, --help
            rc = exc.code
        err = capsys.readouterr().err
        assert rc == 0, f"{cmd}: exit {rc}: {err.strip()[-500:]}"
    else:
        env_path = f"{ROOT / '.venv' / 'bin'}:{Path(sys.executable).parent}"
        proc = subprocess.run(
            ["bash", "-c", f'export PATH="{env_path}:$PATH"; {cmd}'], cwd=ws, capture_output=True, text=True
        )
        assert proc.returncode == 0, f"{cmd}: exit {proc.returncode}: {proc.stderr.strip()[-500:]}"


@pytest.mark.render
@pytest.mark.parametrize("where,lang,cmd", RUNS, ids=[w for w, _, _ in RUNS])
def test_fenced_command_runs(where, lang, cmd, workspace, monkeypatch, capsys):
    monkeypatch.chdir(workspace)
    monkeypatch.setenv("MBCAPTURE_SET", TINY)
    # a block may add scene folders (docs/scenes.md): undone after it, as monkeypatch restores what it set
    monkeypatch.setenv("MBCAPTURE_SCENE_PATH", os.environ.get("MBCAPTURE_SCENE_PATH", ""))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the $MBCAPTURE_SET notice
        if lang == "python":
            exec(compile(cmd, where, "exec"), {"__name__": "__docs__"})
        else:
            run_command(cmd, workspace, capsys)


def test_commands_were_found():
    """The extraction sees the quick start, the Use block and the inline mentions."""
    shown = {c for _, _, lang, c in FENCED if lang == "sh"}
    assert {"make capture", "make test", "mbcapture scenes"} <= shown
    assert any(c.startswith("mbcapture run metronome_hdr") for c in shown)  # a shipped config by name
    assert any(lang == "python" for _, _, lang, _ in FENCED)
    assert any(t.startswith("--set ") for _, _, t in INLINE) and any(
        t.startswith("python scripts/") for _, _, t in INLINE
    )
    shown |= {step for c in shown if c.startswith("make ") for step in make_recipe(c.split()[1], ROOT / "Makefile")}
    for cmd, (reason, _) in NOT_RUN.items():  # no stale entries: each is a command the docs show
        assert reason and cmd in shown, cmd


# ----------------------------------------------------------------------------- checking inline code
def _placeholder(word: str) -> bool:
    """DIR, NAME, KEY=VALUE, section.key=VALUE, app.name=...: a synopsis's stand-in, not a value."""
    value = word.split("=", 1)[-1]
    return bool(re.fullmatch(r"[A-Z][A-Z_]*|\.\.\.", value))


def _words(span: str) -> list[str]:
    """The words of an inline command; a synopsis's optional brackets ([--out DIR]) removed."""
    try:
        words = shlex.split(span)
    except ValueError:
        words = span.split()
    if words and words[0] == "--set":
        return words
    return [w.lstrip("[").rstrip("]") for w in words if w.lstrip("[").rstrip("]")]


def _options(parser) -> set[str]:
    return {o for a in parser._actions for o in a.option_strings}


def check_inline(span: str) -> None:
    from mbcapture.cli import _parser
    from mbcapture.config import load_config

    words = _words(span)
    prog, args = words[0], words[1:]
    if prog == "--set":
        if not any(_placeholder(a) for a in args):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                load_config(DEFAULT_CONFIG, args)  # raises ConfigError if the example is wrong
    elif prog == "mbcapture":
        parser = _parser()
        subs = next(a for a in parser._actions if a.dest == "command").choices
        known = _options(parser)
        positional = [a for a in args if not a.startswith("-")]
        if positional and positional[0] in subs:
            known |= _options(subs[positional[0]])
        elif positional and not _placeholder(positional[0]):
            raise AssertionError(f"`{span}`: no subcommand {positional[0]!r} (expected one of {sorted(subs)})")
        for a in args:
            if a.startswith("--"):
                assert a.split("=")[0] in known, f"`{span}`: no option {a.split('=')[0]}"
    elif prog == "python":
        if args[0] == "-m":
            import importlib.util

            assert importlib.util.find_spec(args[1]), f"`{span}`: no module {args[1]}"
            return
        script = ROOT / args[0]
        assert script.is_file(), f"`{span}`: no file {args[0]}"
        source = script.read_text()
        for a in args[1:]:
            if a.startswith("--"):
                assert f'"{a.split("=")[0]}"' in source, f"`{span}`: {args[0]} has no option {a}"
    elif prog in ("pytest", ".venv/bin/pytest"):
        conftest = (ROOT / "tests" / "conftest.py").read_text()
        for a in args:
            if a.startswith("--"):
                assert f'"{a.split("=")[0]}"' in conftest, f"`{span}`: no pytest option {a} in tests/conftest.py"
            elif "/" in a or a.endswith(".py"):
                assert (ROOT / a.split("::")[0]).exists(), f"`{span}`: no file {a}"
    elif prog == "make":
        text = (ROOT / "Makefile").read_text()
        for target in args:
            assert re.search(rf"^{re.escape(target)}:", text, re.M), f"`{span}`: no make target {target}"


@pytest.mark.parametrize("where,line,span", INLINE, ids=[f"{f}:{n}" for f, n, _ in INLINE])
def test_inline_command_is_valid(where, line, span):
    check_inline(span)


def test_inline_check_catches_what_went_wrong_before():
    """The README's old `--set scene.radiance=[1,1,1]` on the default (metronome) config, a missing
    option and a missing script fail the check."""
    from mbcapture.errors import ConfigError

    with pytest.raises(ConfigError, match="scene.radiance: unknown key"):
        check_inline("--set scene.radiance=[1,1,1]")
    with pytest.raises(AssertionError, match="no option --fast"):
        check_inline("mbcapture figures --fast")
    with pytest.raises(AssertionError, match="no file"):
        check_inline("python scripts/nope.py --out DIR")
    check_inline("mbcapture figures [--out DIR] [--quick] [--only NAME ...]")  # a synopsis is fine


def test_help_examples_load_on_the_default_config():
    """`mbcapture run --help` shows --set examples; each loads on configs/metronome_hdr.yaml."""
    from mbcapture.cli import _parser
    from mbcapture.config import load_config

    run = next(a for a in _parser()._actions if a.dest == "command").choices["run"]
    text = next(a for a in run._actions if a.dest == "overrides").help
    examples = re.findall(r"\b([a-z_]+\.[a-z_.]+=[^\s,)]+)", text)
    assert len(examples) >= 2, text
    for ex in examples:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            load_config(DEFAULT_CONFIG, [ex])
