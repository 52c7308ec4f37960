"""Every subcommand's bad arguments: one line on stderr naming the option, exit status 2, no traceback,
and no work done (each case fails before anything is built, rendered or written)."""

from __future__ import annotations

import pytest

from kdtrace.cli import main

# (arguments, what the one line must contain); {file} is an existing file, {folder} an existing
# folder, {missing} a path that does not exist
CASES = [
    (["no-such-command"], "argument command: invalid choice"),
    (["--config", "{missing}", "scenes"], "argument --config: {missing}: no such file"),
    (["--config", "{folder}", "scenes"], "argument --config: {folder} is a folder"),
    (["--config", "{file}", "scenes"], "unknown section"),
    (["build", "no-such-scene"], "argument scene: unknown scene 'no-such-scene'; available: bunny"),
    (["build", "{missing}.obj"], "argument scene: {missing}.obj: no such scene file"),
    (["build", "{folder}.toml"], "argument scene: {folder}.toml is a folder, not a scene file"),
    (["build", "cbox-original", "--variant", "fast"], "argument --variant: invalid choice: 'fast'"),
    (["build"], "the following arguments are required: scene"),
    (["check-embree", "cbox-original", "--rays", "0"], "argument --rays: must be an integer >= 1, got '0'"),
    (["check-embree", "cbox-original", "--rays", "many"], "argument --rays: not an integer: 'many'"),
    (["check-embree", "cbox-original", "--seed", "-1"], "argument --seed: must be an integer >= 0"),
    (["check-embree", "cbox-original", "--accelerator", ""], "argument --accelerator: empty plug-in name"),
    (["check-embree", "cbox-original", "--accelerator", "warp-drive"], "--accelerator: plug-in 'warp-drive': no such name"),
    (["check-embree", "cbox-original", "--accelerator", "no_such_module_q:make"], "--accelerator: plug-in 'no_such_module_q:make'"),
    (["render", "no-such-scene"], "argument scene: unknown scene"),
    (["render", "cbox-original", "--spp", "0"], "argument --spp: must be an integer >= 1"),
    (["render", "cbox-original", "--spp", "2.5"], "argument --spp: not an integer"),
    (["render", "cbox-original", "--max-depth", "0"], "argument --max-depth: must be an integer >= 1 or -1"),
    (["render", "cbox-original", "--width", "-8"], "argument --width: must be an integer >= 1"),
    (["render", "cbox-original", "--height", "x"], "argument --height: not an integer"),
    (["render", "cbox-original", "--seed", "-3"], "argument --seed: must be an integer >= 0"),
    (["render", "cbox-original", "--variant", "bvh"], "argument --variant: invalid choice"),
    (["render", "cbox-original", "--out", "{file}"], "argument --out: {file} is a file, not a folder"),
    (["compare", "{missing}", "{file}"], "argument test: {missing}: no such file"),
    (["compare", "{file}", "{folder}"], "argument reference: {folder} is a folder, not a file"),
    (["compare", "{file}", "{file}", "--exposure", "0"], "argument --exposure: must be a positive finite number"),
    (["compare", "{file}", "{file}", "--map", "{folder}"], "argument --map: {folder} is a folder, not a file"),
    (["compare", "{file}"], "the following arguments are required: reference"),
    (["reference", "no-such-scene"], "argument scene: unknown scene"),
    (["reference", "cbox-original", "--spp", "0"], "argument --spp: must be an integer >= 1"),
    (["reference", "cbox-original", "--max-depth", "-1"], "argument --max-depth: must be an integer >= 1"),
    (["reference", "cbox-original", "--width", "0"], "argument --width: must be an integer >= 1"),
    (["reference", "cbox-original", "--out", "{file}"], "argument --out: {file} is a file, not a folder"),
    (["compare-mitsuba", "no-such-scene"], "argument scene: unknown scene"),
    (["compare-mitsuba", "cbox-original", "--ref-spp", "zero"], "argument --ref-spp: not an integer"),
    (["compare-mitsuba", "cbox-original", "--height", "0"], "argument --height: must be an integer >= 1"),
    (["compare-mitsuba", "cbox-original", "--out", "{file}"], "argument --out: {file} is a file, not a folder"),
    (["quality", "--scenes", ""], "argument --scenes: empty list"),
    (["quality", "--scenes", "cbox-original,,car"], "argument --scenes: empty name in 'cbox-original,,car'"),
    (["quality", "--scenes", "atlantis"], "--scenes: unknown scenes ['atlantis']"),
    (["quality", "--profile", "huge"], "--profile: unknown reconstruction profile 'huge'; known:"),
    (["quality", "--out", "{file}"], "argument --out: {file} is a file, not a folder"),
    (["dataset", "no-such-scene"], "argument scene: unknown scene"),
    (["dataset", "cbox-original", "--profile", "huge"], "--profile: unknown reconstruction profile 'huge'"),
    (["dataset", "cbox-original", "--workers", "-1"], "argument --workers: must be an integer >= 0"),
    (["dataset", "cbox-original", "--in-process", "--workers", "2"], "--in-process: renders without Dask; it cannot "
                                                                     "be combined with --workers"),
    (["dataset", "cbox-original", "--in-process", "--scheduler", "tcp://h:8786"], "be combined with --scheduler"),
    (["report", "--profile", "huge"], "--profile: unknown profile 'huge'; known profiles:"),
    (["report", "--scenes", ""], "argument --scenes: empty list"),
    (["report", "--scenes", "atlantis"], "--scenes: ['atlantis'] not in profile 'quick'; its scenes:"),
    (["report", "--parts", ""], "argument --parts: empty list"),
    (["report", "--parts", "table1,table9"], "--parts: unknown report parts ['table9']; known: table1"),
    (["report", "--out", "{file}"], "argument --out: {file} is a file, not a folder"),
    (["report", "--accelerator", ","], "argument --accelerator: empty plug-in name"),
    (["report", "--accelerator", "warp-drive"], "--accelerator: plug-in 'warp-drive': no such name"),
    (["report", "--denoiser", "no_such_module_q:make"], "--denoiser: plug-in 'no_such_module_q:make': cannot import"),
    (["report", "--fresh", "--bogus"], "unrecognized arguments: --bogus"),
    (["verdict", "{missing}"], "argument RESULTS_DIR: {missing}: no such folder"),
    (["verdict", "{file}"], "argument RESULTS_DIR: {file} is a file, not a folder"),
    (["verdict", "--profile", "huge"], "--profile: unknown profile 'huge'"),
    (["verdict", "{folder}", "--profile", "paper"], "--profile: picks the results folder only without RESULTS_DIR"),
    (["gate", "--profile", "huge"], "--profile: unknown profile 'huge'"),
    (["production", "--profile", "huge"], "--profile: unknown profile 'huge'"),
    (["production", "--triangles", "0"], "argument --triangles: must be an integer >= 1, got '0'"),
    (["production", "--out", "{file}"], "argument --out: {file} is a file, not a folder"),
    (["gate", "--out", "{missing}"], "argument --out: {missing}: no such folder"),
    (["gate", "--baselines", "{missing}"], "argument --baselines: {missing}: no such folder"),
    (["gate", "--baselines", "{file}"], "argument --baselines: {file} is a file, not a folder"),
    (["update-baseline", "--profile", "huge"], "--profile: unknown profile 'huge'"),
    (["update-baseline", "--out", "{file}"], "argument --out: {file} is a file, not a folder"),
    (["update-baseline", "--baselines", "{file}"], "argument --baselines: {file} is a file, not a folder"),
]


@pytest.mark.parametrize(("arguments", "expected"), CASES, ids=[" ".join(a) or "none" for a, _ in CASES])
def test_a_bad_argument_is_one_line_naming_the_option_and_exit_2(arguments, expected, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("KDTRACE_CACHE", str(tmp_path / "cache"))
    paths = {"file": tmp_path / "notes.txt", "folder": tmp_path / "folder", "missing": tmp_path / "missing"}
    paths["file"].write_text("[nonsense]\n")
    paths["folder"].mkdir()
    (tmp_path / "folder.toml").mkdir()
    arguments = [argument.format(**paths) for argument in arguments]
    assert main(arguments) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.count("\n") == 1 and "Traceback" not in captured.err
    assert expected.format(**paths) in captured.err
    assert sorted(path.name for path in tmp_path.iterdir()) == ["folder", "folder.toml", "notes.txt"]  # nothing written


def test_help_exits_0(capsys):
    assert main(["render", "--help"]) == 0
    assert "--max-depth" in capsys.readouterr().out
