"""Bad inputs to every user-facing tool, one table row per case.

Each row runs a tool the way a user does (its console entry point with ``sys.argv``, in-process; one row goes
through the installed console script) and checks the contract the tools document: exit status 1 (130 for Ctrl+C),
exactly one error line on stderr that names the file or value at fault, no Python traceback, nothing written (the
whole test folder, the working directory included, is the same before and after, file contents hashed) and nothing
rendered or trained. The runs are fake (a nerfacto-cpu config.yml and a dummy checkpoint): every case must fail before
a model is loaded, so the module needs no NeRF and runs in seconds.
"""

from __future__ import annotations

import hashlib
import json
import os
import signal
import socket
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from nerfuser_ns.method_configs.nerfacto_cpu import nerfacto_cpu_config

from nerfuser_ns import runs, sim3
from nerfuser_ns.spec import write_fusion_spec

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
IS_ROOT = hasattr(os, "geteuid") and os.geteuid() == 0


# ----------------------------------------------------------------------------------------------------------------------
# The workspace every row builds its inputs in


def fake_run(root: Path, name: str) -> Path:
    """A run folder that parses as a nerfstudio run (config.yml + a checkpoint file); nothing is trained."""
    config = nerfacto_cpu_config(10)
    config.experiment_name, config.timestamp, config.output_dir = name, "run", root
    run_dir = root / name / "nerfacto-cpu" / "run"
    (run_dir / "nerfstudio_models").mkdir(parents=True)
    (run_dir / "config.yml").write_text(yaml.dump(config))
    (run_dir / "nerfstudio_models" / "step-000000009.ckpt").write_bytes(b"not loaded by these tests")
    return run_dir / "config.yml"


@dataclass
class Workspace:
    root: Path
    """Everything a row reads or may write lies under it (the working directory is ``root/cwd``)."""
    a: Path
    b: Path
    """Two fake runs' config.yml."""
    undo: list[Callable[[], None]] = field(default_factory=list)

    def write(self, rel: str, text: str) -> Path:
        path = self.root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
        return path

    def spec(self, rel: str, value: dict) -> Path:
        return self.write(rel, json.dumps(value))

    def registration(self, rel: str, transform_b: np.ndarray, checkpoints: bool = False) -> Path:
        """A registration file (the format ns-nerfuser-register writes) for runs a and b."""
        nerfs = []
        for name, config, T in (("a", self.a, np.eye(4)), ("b", self.b, transform_b)):
            entry = {"name": name, "config": str(config), "T_to_reference": np.asarray(T).tolist()}
            if checkpoints:
                entry["checkpoint"] = runs.checkpoint_identity(config)
            nerfs.append(entry)
        record = {"format_version": 1, "kind": "nerfuser_registration", "reference": {"index": 0, "name": "a"},
                  "nerfs": nerfs, "pairs": []}  # fmt: skip
        return self.write(rel, json.dumps(record))


@dataclass
class Call:
    """What a row runs and what its one error line must contain."""

    argv: list[str]
    fragments: list[str]
    env: dict[str, str] = field(default_factory=dict)
    must_not_exist: list[Path] = field(default_factory=list)
    """Besides the snapshot: paths the tool must not create (named so a failure says what went wrong)."""
    patches: list[tuple[object, str, object]] = field(default_factory=list)
    """(object, attribute, value) set for the call (in-process rows only)."""


@dataclass(frozen=True)
class Row:
    tool: str
    build: Callable[[Workspace], Call]
    rc: int = 1
    console_script: bool = False
    """Run the installed console script in a subprocess instead of its entry point in-process."""


SHEAR = np.eye(4)
SHEAR[0, 1] = 0.3
T_B = sim3.make_sim3(np.eye(3), np.array([1.0, 0.0, 0.5]), 0.8)


def _register(ws: Workspace, *args: str, configs: list[Path] | None = None, output: Path | None = None) -> list[str]:
    configs = [ws.a, ws.b] if configs is None else configs
    output = ws.root / "reg" / "registration.json" if output is None else output
    return ["--configs", *map(str, configs), "--output", str(output), *args]


def _train(spec: Path, ws: Workspace, *args: str) -> list[str]:
    return ["nerfuser", "--data", str(spec), "--output-dir", str(ws.root / "out"), *args]


def _train_call(ws: Workspace, spec: Path, fragments: list[str], *args: str, env: dict | None = None) -> Call:
    return Call(_train(spec, ws, *args), ["nerfuser: ", *fragments], env=env or {}, must_not_exist=[ws.root / "out"])


# ----------------------------------------------------------------------------------------------------------------------
# ns-nerfuser-register


def reg_one_config(ws):
    return Call(_register(ws, configs=[ws.a]), ["at least 2 runs", "--configs", "got 1"])


def reg_missing_config(ws):
    missing = ws.root / "outputs" / "gone" / "nerfacto" / "run" / "config.yml"
    return Call(_register(ws, configs=[ws.a, missing]), [str(missing), "no such file", "pass the config.yml"])


def reg_not_a_nerfstudio_config(ws):
    other = ws.write("outputs/other/x/run/config.yml", "learning_rate: 0.01\nsteps: 100\n")
    return Call(_register(ws, configs=[ws.a, other]), [str(other), "not a nerfstudio run config"])


def reg_unreadable_yaml(ws):
    other = ws.write("outputs/other/x/run/config.yml", "pipeline: [unclosed\n")
    return Call(_register(ws, configs=[ws.a, other]), [str(other), "not a readable nerfstudio config"])


def reg_os_system_tag(ws):
    marker = ws.root / "pwned"
    evil = ws.write("outputs/evil/x/run/config.yml", f'!!python/object/apply:os.system ["touch {marker}"]\n')
    return Call(_register(ws, configs=[ws.a, evil]), [str(evil), "refusing !!python/object/apply:os.system"],
                must_not_exist=[marker])  # fmt: skip


def reg_os_system_tag_inside_a_real_config(ws):
    """The tag deep inside an otherwise genuine nerfstudio config (what a tampered download looks like)."""
    marker = ws.root / "pwned"
    text = ws.b.read_text()
    assert "experiment_name: b\n" in text
    tag = f'!!python/object/apply:os.system ["touch {marker}"]'
    text = text.replace("experiment_name: b\n", f"experiment_name: {tag}\n")
    evil = ws.write("outputs/evil/nerfacto-cpu/run/config.yml", text)
    (evil.parent / "nerfstudio_models").mkdir()
    (evil.parent / "nerfstudio_models" / "step-000000009.ckpt").write_bytes(b"x")
    return Call(_register(ws, configs=[ws.a, evil]), [str(evil), "refusing !!python/object/apply:os.system"],
                must_not_exist=[marker])  # fmt: skip


def reg_output_is_a_config(ws):
    return Call(_register(ws, output=ws.b), ["--output", str(ws.b.parent), "inside the run folder", "elsewhere"])


def reg_output_inside_a_run(ws):
    out = ws.a.parent / "registration.json"
    return Call(_register(ws, output=out), ["--output", str(out), "inside the run folder", "elsewhere"])


def reg_output_is_a_folder(ws):
    folder = ws.root / "results"
    folder.mkdir()
    return Call(_register(ws, output=folder), ["--output", str(folder), "is a folder", "pass a file path"])


def reg_output_parent_is_a_file(ws):
    parent = ws.write("notes.txt", "a file, not a folder\n")
    return Call(_register(ws, output=parent / "registration.json"), ["--output", str(parent), "is not a folder"])


def reg_output_in_a_read_only_folder(ws):
    folder = ws.root / "read_only"
    folder.mkdir()
    folder.chmod(0o555)
    ws.undo.append(lambda: folder.chmod(0o755))
    # root writes through chmod 555: there the OS's answer for an ordinary user is given by os.access
    real = os.access

    def access(path, mode, *args, **kwargs) -> bool:
        return False if Path(path) == folder and mode & os.W_OK else real(path, mode, *args, **kwargs)

    return Call(_register(ws, output=folder / "registration.json"), [str(folder), "is not writable"],
                patches=[(os, "access", access)] if IS_ROOT else [])  # fmt: skip


def reg_device_banana(ws):
    return Call(_register(ws, "--device", "banana"), ["--device 'banana'", "is not a torch device", "cpu"])


def reg_device_cuda_without_cuda(ws):
    return Call(_register(ws, "--device", "cuda"), ["--device 'cuda'", "is not on this machine", "cpu"])


def reg_nan_center(ws):
    return Call(_register(ws, "--sampling.center", "0", "nan", "0"), ["--sampling.center", "nan", "must be finite"])


def reg_tiny_render_size(ws):
    return Call(_register(ws, "--sampling.size", "4"), ["--sampling.size must be >= 16"])


def reg_data_count(ws):
    data = ws.root / "capture_a"
    data.mkdir()
    return Call(_register(ws, "--data", str(data)), ["--data names 1 dataset folders for 2 runs", "one per run"])


def reg_data_not_a_dataset(ws):
    empty = ws.root / "not_a_dataset"
    empty.mkdir()
    return Call(_register(ws, "--data", str(empty), str(empty)), [str(empty), "not a dataset folder"])


def reg_data_missing(ws):
    gone = ws.root / "moved_away"
    return Call(_register(ws, "--data", str(gone), str(gone)), [str(gone), "no such folder"])


def reg_interrupted(ws):
    """Ctrl+C once the inputs checked out (the registration itself is replaced): 130, one line, no output."""
    from nerfuser_ns.scripts import register as register_cli

    return Call(_register(ws), ["interrupted: nothing written"], patches=[(register_cli, "register", _interrupt)])


# ----------------------------------------------------------------------------------------------------------------------
# ns-train nerfuser


def train_good_spec(ws: Workspace) -> Path:
    ws.registration("fusion/registration.json", T_B)
    return write_fusion_spec(ws.root / "fusion" / "fusion.json", [ws.a, ws.b])


def train_negative_gamma(ws):
    return _train_call(ws, train_good_spec(ws), ["gamma must be >= 0, got -1.0"], "--pipeline.model.gamma=-1")


def train_nan_gamma(ws):
    return _train_call(ws, train_good_spec(ws), ["gamma must be >= 0, got nan"], "--pipeline.model.gamma", "nan")


def train_tau_half(ws):
    return _train_call(ws, train_good_spec(ws), ["tau must be >= 1", "0.5"], "--pipeline.model.tau", "0.5")


def train_env_gamma(ws):
    spec = train_good_spec(ws)
    return _train_call(ws, spec, ["NERFUSER_GAMMA must be a number, got 'fast'"], env={"NERFUSER_GAMMA": "fast"})


def train_env_method(ws):
    spec = train_good_spec(ws)
    return _train_call(ws, spec, ["unknown blend method 'idw-4d'", "idw-sample"],
                       env={"NERFUSER_BLEND_METHOD": "idw-4d"})  # fmt: skip


def train_env_appearance(ws):
    spec = train_good_spec(ws)
    return _train_call(ws, spec, ["NERFUSER_APPEARANCE_MATCHING must be one of", "'maybe'"],
                       env={"NERFUSER_APPEARANCE_MATCHING": "maybe"})  # fmt: skip


def train_no_runs_no_registration(ws):
    spec = ws.spec("fusion/fusion.json", {"test_data": None})
    return _train_call(ws, spec, [str(spec), "no 'runs' and no registration file", "registration.json"])


def train_missing_run(ws):
    missing = ws.root / "outputs" / "gone" / "nerfacto-cpu" / "run" / "config.yml"
    spec = write_fusion_spec(ws.root / "fusion" / "fusion.json", [ws.a, missing])
    return _train_call(ws, spec, [str(spec), str(missing), "no such file"])


def train_sheared_registration(ws):
    reg = ws.registration("fusion/registration.json", SHEAR)
    spec = write_fusion_spec(ws.root / "fusion" / "fusion.json", [ws.a, ws.b])
    return _train_call(ws, spec, [str(reg), "not a scaled rotation"])


def train_stale_registration(ws):
    reg = ws.registration("fusion/registration.json", T_B, checkpoints=True)
    (ws.b.parent / "nerfstudio_models" / "step-000000019.ckpt").write_bytes(b"trained further")
    spec = write_fusion_spec(ws.root / "fusion" / "fusion.json", [ws.a, ws.b])
    return _train_call(ws, spec, [str(reg), "changed since it was registered", "re-run ns-nerfuser-register"])


# ----------------------------------------------------------------------------------------------------------------------
# ns-nerfuser-view


def view_missing_spec(ws):
    missing = ws.root / "fusion" / "fusion.json"
    return Call([str(missing)], ["ns-nerfuser-view: ", str(missing), "no such file or folder"])


def view_missing_spec_with_brackets(ws):
    """The path is printed as written: ``[old]`` is no console markup to swallow."""
    missing = ws.root / "fusion" / "fusion[old].json"
    return Call([str(missing)], ["ns-nerfuser-view: ", str(missing), "no such file or folder"])


def view_port_out_of_range(ws):
    return Call([str(train_good_spec(ws)), "--port", "70000"], ["--port 70000", "not a TCP port"])


def view_unknown_host(ws):
    return Call([str(train_good_spec(ws)), "--host", "no-such-host.invalid"],
                ["--host 'no-such-host.invalid'", "cannot be resolved", "127.0.0.1"])  # fmt: skip


def view_a_non_fused_run(ws):
    return Call([str(ws.a)], [str(ws.a), "not a fused one", "ns-viewer"])


# ----------------------------------------------------------------------------------------------------------------------
# python -m nerfuser_ns.bench.ground_truth


def score_registration_file(ws: Workspace) -> Path:
    return ws.registration("reg/registration.json", T_B)


def score_gt(ws: Workspace, T: np.ndarray, name: str) -> Path:
    return ws.write(f"gt/{name}.json", json.dumps({"nerf_to_world": np.asarray(T).tolist()}))


def score_output_is_input(ws):
    reg = score_registration_file(ws)
    gts = [score_gt(ws, np.eye(4), "a"), score_gt(ws, T_B, "b")]
    return Call([str(reg), "--gt-transforms", *map(str, gts), "--output", str(reg)],
                ["--output", str(reg), "is the input registration file", "elsewhere"])  # fmt: skip


def score_sheared_truth(ws):
    reg = score_registration_file(ws)
    gts = [score_gt(ws, np.eye(4), "a"), score_gt(ws, SHEAR, "b")]
    return Call([str(reg), "--gt-transforms", *map(str, gts)], [str(gts[1]), "not a scaled rotation"])


def score_bracketed_truth(ws):
    """A message holding brackets (the bad row, a path with [..]) prints as written, not as console markup."""
    reg = score_registration_file(ws)
    bad = np.eye(4)
    bad[3] = [0.0, 0.0, 1.0, 1.0]
    gts = [score_gt(ws, np.eye(4), "a"), score_gt(ws, bad, "[red]b")]
    return Call([str(reg), "--gt-transforms", *map(str, gts)],
                [str(gts[1]), "last row must be [0, 0, 0, 1], got [0.0, 0.0, 1.0, 1.0]"])  # fmt: skip


def score_wrong_count(ws):
    reg = score_registration_file(ws)
    return Call([str(reg), "--gt-transforms", str(score_gt(ws, np.eye(4), "a"))],
                ["--gt-transforms has 1 files for 2 NeRFs"])  # fmt: skip


def score_no_reference(ws):
    """A hand-written registration without "reference" whose transforms are none of them identity."""
    reg = ws.write("reg/hand.json", json.dumps({"kind": "nerfuser_registration", "nerfs": [
        {"name": n, "config": str(c), "T_to_reference": T_B.tolist()} for n, c in (("a", ws.a), ("b", ws.b))]}))
    gts = [score_gt(ws, np.eye(4), "a"), score_gt(ws, T_B, "b")]
    return Call([str(reg), "--gt-transforms", *map(str, gts)], ["names no reference NeRF", '"reference"'])


# ----------------------------------------------------------------------------------------------------------------------
# The table


def defect(reason: str) -> pytest.MarkDecorator:
    """A row the tool fails today (strict: the mark must go when the tool is fixed)."""
    return pytest.mark.xfail(strict=True, reason=reason)


ROWS = [
    pytest.param(Row("register", reg_one_config), id="register-fewer-than-2-configs"),
    pytest.param(Row("register", reg_missing_config), id="register-missing-config"),
    pytest.param(Row("register", reg_not_a_nerfstudio_config), id="register-yaml-not-a-nerfstudio-config"),
    pytest.param(Row("register", reg_unreadable_yaml), id="register-unparsable-yaml"),
    pytest.param(Row("register", reg_os_system_tag), id="register-os-system-tag-refused-not-run"),
    pytest.param(Row("register", reg_os_system_tag_inside_a_real_config), id="register-os-system-tag-nested"),
    pytest.param(Row("register", reg_output_is_a_config), id="register-output-is-a-runs-config"),
    pytest.param(Row("register", reg_output_inside_a_run), id="register-output-inside-a-run-folder"),
    pytest.param(Row("register", reg_output_is_a_folder), id="register-output-is-an-existing-folder"),
    pytest.param(Row("register", reg_output_parent_is_a_file), id="register-output-parent-is-a-file"),
    pytest.param(Row("register", reg_output_in_a_read_only_folder), id="register-output-in-read-only-folder"),
    pytest.param(Row("register", reg_device_banana), id="register-device-banana"),
    pytest.param(
        Row("register", reg_device_cuda_without_cuda),
        id="register-device-cuda-without-cuda",
        marks=pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA"),
    ),
    pytest.param(Row("register", reg_nan_center), id="register-nan-sampling-center"),
    pytest.param(Row("register", reg_tiny_render_size), id="register-sampling-size-4"),
    pytest.param(Row("register", reg_data_count), id="register-data-count-differs-from-configs"),
    pytest.param(Row("register", reg_data_not_a_dataset), id="register-data-not-a-dataset"),
    pytest.param(Row("register", reg_data_missing), id="register-data-missing-folder"),
    pytest.param(Row("register", reg_interrupted, rc=130), id="register-ctrl-c"),
    pytest.param(Row("train", train_negative_gamma), id="train-gamma-negative"),
    pytest.param(Row("train", train_nan_gamma), id="train-gamma-nan"),
    pytest.param(Row("train", train_tau_half), id="train-tau-0.5"),
    pytest.param(Row("train", train_env_gamma), id="train-env-NERFUSER_GAMMA-not-a-number"),
    pytest.param(Row("train", train_env_method), id="train-env-NERFUSER_BLEND_METHOD-unknown"),
    pytest.param(Row("train", train_env_appearance), id="train-env-NERFUSER_APPEARANCE_MATCHING-not-a-switch"),
    pytest.param(Row("train", train_no_runs_no_registration), id="train-spec-without-runs-or-registration"),
    pytest.param(Row("train", train_missing_run), id="train-spec-names-a-missing-run"),
    pytest.param(Row("train", train_sheared_registration), id="train-registration-sheared-transform"),
    pytest.param(Row("train", train_stale_registration), id="train-registration-stale-checkpoint"),
    pytest.param(Row("view", view_missing_spec, console_script=True), id="view-missing-spec-console-script"),
    pytest.param(Row("view", view_missing_spec_with_brackets), id="view-missing-spec-brackets-kept"),
    pytest.param(Row("view", view_port_out_of_range), id="view-port-70000"),
    pytest.param(Row("view", view_unknown_host), id="view-host-unresolvable"),
    pytest.param(Row("view", view_a_non_fused_run), id="view-non-fused-run-config"),
    pytest.param(Row("score", score_output_is_input), id="score-output-is-the-input-registration"),
    pytest.param(Row("score", score_sheared_truth), id="score-sheared-gt-transform"),
    pytest.param(Row("score", score_bracketed_truth), id="score-gt-transform-bad-last-row-brackets-kept"),
    pytest.param(Row("score", score_wrong_count), id="score-wrong-number-of-gt-transforms"),
    pytest.param(Row("score", score_no_reference), id="score-hand-written-registration-without-reference"),
]


# ----------------------------------------------------------------------------------------------------------------------
# Running a row


def _entrypoint(tool: str) -> tuple[str, Callable[[], None]]:
    """(argv[0], the function the console script calls): imported here so a broken tool fails only its rows."""
    if tool == "register":
        from nerfuser_ns.scripts.register import entrypoint

        return "ns-nerfuser-register", entrypoint
    if tool == "train":
        from nerfstudio.scripts.train import entrypoint

        return "ns-train", entrypoint
    if tool == "view":
        from nerfuser_ns.scripts.view import entrypoint

        return "ns-nerfuser-view", entrypoint
    from nerfuser_ns.bench.ground_truth import entrypoint

    return "python -m nerfuser_ns.bench.ground_truth", entrypoint


def _no_work(*args, **kwargs):
    raise AssertionError("a bad input got as far as loading a model, training or rendering")


_REAL_GETADDRINFO = socket.getaddrinfo


def _no_network(host, *args, **kwargs):
    """getaddrinfo for numeric addresses and localhost only: the tests never query a name server."""
    if host in (None, "localhost") or _is_numeric(host):
        return _REAL_GETADDRINFO(host, *args, **kwargs)
    raise socket.gaierror(socket.EAI_NONAME, "Name or service not known (tests resolve no names)")


def _is_numeric(host) -> bool:
    try:
        socket.inet_pton(socket.AF_INET6 if ":" in str(host) else socket.AF_INET, str(host))
    except (OSError, ValueError):
        return False
    return True


def run_in_process(tool: str, call: Call, monkeypatch, capsys) -> tuple[int, str, str]:
    """The console script's entry point with ``sys.argv``; the exit status Python would give the process."""
    import nerfstudio.scripts.train as ns_train

    prog, entry = _entrypoint(tool)
    monkeypatch.setattr(sys, "argv", [prog, *call.argv])
    monkeypatch.setattr(runs, "load_run", _no_work)
    monkeypatch.setattr(ns_train, "launch", _no_work)
    monkeypatch.setattr(socket, "getaddrinfo", _no_network)
    for key, value in call.env.items():
        monkeypatch.setenv(key, value)
    for obj, name, value in call.patches:
        monkeypatch.setattr(obj, name, value)
    sigterm = signal.getsignal(signal.SIGTERM)  # ns-nerfuser-view installs its own
    try:
        entry()
        rc = 0
    except SystemExit as e:
        if e.code is None or isinstance(e.code, int):
            rc = e.code or 0
        else:  # what the interpreter does with sys.exit("message")
            print(e.code, file=sys.stderr)
            rc = 1
    finally:
        signal.signal(signal.SIGTERM, sigterm)
    out, err = capsys.readouterr()
    return rc, out, err


def _interrupt(*args, **kwargs):
    raise KeyboardInterrupt


def run_console_script(tool: str, call: Call, cwd: Path) -> tuple[int, str, str]:
    script = {"register": "ns-nerfuser-register", "train": "ns-train", "view": "ns-nerfuser-view"}[tool]
    env = {**os.environ, "PYTHONPATH": str(ROOT), **call.env}
    proc = subprocess.run([str(BIN / script), *call.argv], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=300)  # fmt: skip
    return proc.returncode, proc.stdout, proc.stderr


def snapshot(root: Path) -> dict[str, str]:
    """Every path under ``root``: folders as such, files by content hash."""
    out = {}
    for p in sorted(root.rglob("*")):
        rel = str(p.relative_to(root))
        out[rel] = "folder" if p.is_dir() else hashlib.sha256(p.read_bytes()).hexdigest()
    return out


@pytest.fixture
def ws(tmp_path, monkeypatch):
    outputs = tmp_path / "outputs"
    workspace = Workspace(tmp_path, fake_run(outputs, "a"), fake_run(outputs, "b"))
    (tmp_path / "cwd").mkdir()
    monkeypatch.chdir(tmp_path / "cwd")  # a default output path would land here, inside the snapshot
    for key in ("NERFUSER_BLEND_METHOD", "NERFUSER_GAMMA", "NERFUSER_TAU"):
        monkeypatch.delenv(key, raising=False)
    yield workspace
    for undo in workspace.undo:
        undo()


@pytest.mark.parametrize("row", ROWS)
def test_bad_input_fails_with_one_line_and_leaves_everything_as_it_was(row: Row, ws, monkeypatch, capsys):
    call = row.build(ws)
    before = snapshot(ws.root)
    if row.console_script:
        rc, out, err = run_console_script(row.tool, call, ws.root / "cwd")
    else:
        rc, out, err = run_in_process(row.tool, call, monkeypatch, capsys)
    after = snapshot(ws.root)

    assert rc == row.rc, (rc, err[-3000:])
    assert "Traceback" not in out + err, err[-3000:]
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, "expected exactly one line on stderr:\n" + err
    for fragment in call.fragments:
        assert fragment in lines[0], (fragment, lines[0])
    for path in call.must_not_exist:
        assert not path.exists(), f"{path} was created"
    created = sorted(set(after) - set(before))
    removed = sorted(set(before) - set(after))
    changed = sorted(p for p in set(before) & set(after) if before[p] != after[p])
    assert (created, removed, changed) == ([], [], []), "files created / removed / changed"
