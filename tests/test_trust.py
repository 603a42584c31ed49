"""A run directory is data, never code (docs/configuration.md, "The trust model"): the one loader
of checkpoints refuses every payload this package does not write, and runs none of it; a
checkpoint must say which run it is, or be adopted; a run directory holds folders and regular
files of one link only; every file of it is read bounded; every refusal is one line."""

from __future__ import annotations

import json
import os
import resource
import shutil
import signal
import zlib

import pytest
import torch

from armeta_rl.cli import evaluate, train
from armeta_rl.cli.compose import check_jobs
from armeta_rl.cli.failures import Refused
from armeta_rl.cli.jobs import make_job
from armeta_rl.config import read_run_config
from armeta_rl.errors import ConfigError
from armeta_rl.job import Job
from armeta_rl.trainers import training
from armeta_rl.trainers.checkpoint import MANIFEST, seal
from armeta_rl.trainers.players import load_players
from armeta_rl.trainers.run_dir import LOCK_FILE, run_lock, write_text_atomically
from armeta_rl.trainers.training import run_training
from conftest import SMALL_RUN, in_process, refusal, train_config

RUN = (*SMALL_RUN, "method=ar_maml", "trainer.meta_batch=5", "logger=csv",
       "trainer.log_every=1", "trainer.checkpoint_every=2", "trainer.density_every=2")
"""A six-iteration AR-MAML run with checkpoints and density frames at 2, 4 and 6, CSV logs."""
LEADER = "checkpoints/checkpoint-000000000004/components/0000-leader"


@pytest.fixture(scope="module")
def stopped(tmp_path_factory):
    """The run stopped after iteration 4 (checkpoints at 2 and 4)."""
    run_dir = tmp_path_factory.mktemp("stopped") / "run"
    run_training(Job(train_config(*RUN, "trainer.stop_at=4"), run_dir), progress=False)
    return run_dir


@pytest.fixture
def run_dir(tmp_path, stopped):
    """A copy of the stopped run to damage."""
    shutil.copytree(stopped, tmp_path / "run")
    return tmp_path / "run"


def resume(run_dir, *overrides):
    run_training(make_job([f"resume={run_dir}", *overrides]), progress=False)


class Pickled:
    """An object whose unpickling creates ``marker``: what a hostile payload does."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


def resealed(checkpoint, edit=lambda manifest: None):
    """``checkpoint``'s manifest changed by ``edit`` and sealed again with the package's own
    ``seal``, as anyone can: its digests then match whatever it holds."""
    manifest = json.loads((checkpoint / MANIFEST).read_text())
    edit(manifest)
    (checkpoint / MANIFEST).write_text(json.dumps(manifest))
    seal(checkpoint, manifest["metadata"].get("identity"))


def test_a_memory_mapped_payload_with_a_pickled_field_is_refused_and_runs_nothing(
        run_dir, tmp_path):
    """A leader payload as a TensorDict memory map (which torchrl's own load would take, and
    whose non-tensor field it would unpickle), listed in the manifest and resealed: resume and
    armeta-eval refuse it naming the file, and the field's code never runs."""
    import tensordict

    marker = tmp_path / "marker"
    component = run_dir / LEADER
    data = tensordict.TensorDict({"x": torch.zeros(1)}, batch_size=[])
    data.set_non_tensor("payload", Pickled(marker))
    (component / "state.pt").unlink()
    tensordict.save(data, component / "state")
    (component / "state.json").write_text('{"kind":"tensor","key":"x","device":"cpu"}')
    files = sorted(str(p.relative_to(component)) for p in component.rglob("*") if p.is_file())
    resealed(component.parents[1], lambda m: m["components"]["leader"].update(files=files))
    with pytest.raises(ConfigError, match="one state.pt or value.json per component"):
        resume(run_dir)
    with pytest.raises(ConfigError, match="one state.pt or value.json per component"):
        load_players(run_dir, "learner")
    assert not marker.exists()


def test_a_state_pt_holding_another_object_is_refused_in_one_line_naming_it(
        run_dir, tmp_path, capsys):
    """A pickle GLOBAL (``os.system``) in a resealed state.pt: torch's three-line refusal is
    folded into one line that names the file; nothing runs."""
    marker = tmp_path / "marker"
    state_pt = run_dir / LEADER / "state.pt"
    state = torch.load(state_pt, weights_only=True)
    state["payload"] = Pickled(marker)
    torch.save(state, state_pt)
    resealed(state_pt.parents[2])
    line = refusal(evaluate, [f"learner={run_dir}", f"out={tmp_path / 'out.json'}"], capsys)
    assert f"{LEADER}/state.pt holds what torch.load(weights_only=True) refuses" in line
    assert "GLOBAL posix.system" in line and not marker.exists()


@pytest.mark.parametrize("link", ["symbolic", "hard"])
def test_a_payload_or_checkpoint_linked_to_outside_the_run_is_refused(run_dir, tmp_path, link):
    from armeta_rl.run_files import FileRefused, read_file

    state_pt = run_dir / LEADER / "state.pt"
    outside = tmp_path / "outside.pt"
    if link == "symbolic":
        state_pt.rename(outside)
        state_pt.symlink_to(outside)
    else:
        os.link(state_pt, outside)
    with pytest.raises(ConfigError, match="is a link|has 2 hard links"):
        resume(run_dir)
    newest = run_dir / LEADER.split("/components")[0]
    newest.rename(tmp_path / "checkpoint")
    newest.symlink_to(tmp_path / "checkpoint")
    with pytest.raises(FileRefused, match="its folder checkpoint-000000000004 is a link"):
        read_file(newest / MANIFEST, 2**20, run_dir)


def test_a_checkpoint_that_records_no_run_is_refused_unless_adopted(run_dir):
    """Checkpoints whose identity was removed (or that predate identities) are not taken as the
    run's own silently; ``adopt=true`` says they are, and the run finishes from them."""
    for checkpoint in (run_dir / "checkpoints").glob("checkpoint-*"):
        resealed(checkpoint, lambda m: m["metadata"].pop("identity"))
    with pytest.raises(ConfigError, match=r"records no run .* \(benchmark sinusoid_uniform, "
                                          r"method ar_maml, seed 0\): if it is, add adopt=true"):
        resume(run_dir)
    resume(run_dir, "adopt=true")
    assert (run_dir / "eval.json").is_file()
    assert make_job([f"resume={run_dir}"]).config.adopt is False  # a resume's own, not kept


def test_a_lock_file_with_a_second_link_is_refused_and_that_file_untouched(run_dir, tmp_path):
    outside = tmp_path / "outside.txt"
    outside.write_text("keep me\n")
    os.link(outside, run_dir / LOCK_FILE)
    with pytest.raises(ConfigError, match="its run.lock has 2 hard links"), run_lock(
            run_dir, "resume"):
        pass
    assert outside.read_text() == "keep me\n"


@pytest.mark.parametrize("entry,kind", [
    ("logs/scalars/train/leader_loss.csv", "link"), ("armeta-train.log", "link"),
    ("density/iter_000002.png", "pipe"), ("logs/scalars/train/leader_loss.csv", "hard link"),
])
def test_a_run_directory_holding_anything_but_files_and_folders_is_refused_in_one_line(
        run_dir, tmp_path, capsys, entry, kind):
    """A link (a log written or a frame read through it), a pipe (a read waiting forever) or a
    hard link (a log appended to in another place) anywhere in a run: resume refuses it in one
    line before Hydra opens its job log there, and the file outside stays as it was."""
    from armeta_rl.trainers.run_dir import check_contents

    path, outside = run_dir / entry, tmp_path / "outside"
    outside.write_text("keep me\n")
    path.unlink(missing_ok=True)
    {"link": lambda: path.symlink_to(outside), "pipe": lambda: os.mkfifo(path),
     "hard link": lambda: os.link(outside, path)}[kind]()
    with pytest.raises(ConfigError, match=f"its {entry} (is a link|is not a regular file|has 2)"):
        check_contents(run_dir, "resume")
    line = refusal(train, [f"resume={run_dir}"], capsys)
    assert line.startswith(f"armeta-train: error: config key 'resume' = '{run_dir}': its {entry}")
    assert outside.read_text() == "keep me\n"


def test_the_one_reader_refuses_what_is_no_regular_file_of_one_link_within_its_bound(tmp_path):
    from armeta_rl.run_files import FileRefused, read_file

    folder = tmp_path / "run"
    (folder / "sub").mkdir(parents=True)
    (folder / "sub" / "file").write_bytes(b"12345")
    assert read_file(folder / "sub" / "file", 5, folder) == b"12345"
    with pytest.raises(FileRefused, match="has 5 bytes, more than the 4"):
        read_file(folder / "sub" / "file", 4, folder)
    os.mkfifo(folder / "pipe")
    with pytest.raises(FileRefused, match="is a pipe, not a regular file"):
        read_file(folder / "pipe", 5)
    (folder / "link").symlink_to(folder / "sub" / "file")
    with pytest.raises(FileRefused, match="is a link, not a regular file"):
        read_file(folder / "link", 5)
    (tmp_path / "elsewhere").symlink_to(folder / "sub", target_is_directory=True)
    (folder / "linked").symlink_to(tmp_path / "elsewhere")
    with pytest.raises(FileRefused, match="its folder linked is a link"):
        read_file(folder / "linked" / "file", 5, folder)
    os.link(folder / "sub" / "file", folder / "twin")
    with pytest.raises(FileRefused, match="has 2 hard links"):
        read_file(folder / "twin", 5)
    with pytest.raises(FileNotFoundError):
        read_file(folder / "missing", 5)


def test_compressed_files_are_read_whole_and_bounded():
    from armeta_rl.run_files import FileRefused, gunzip

    data = zlib.compress(b"x" * 1000, wbits=16 + zlib.MAX_WBITS)
    assert gunzip(data, 1000, "f.gz") == b"x" * 1000
    with pytest.raises(FileRefused, match="decompresses to more than the 999 bytes"):
        gunzip(data, 999, "f.gz")
    with pytest.raises(FileRefused, match="is cut short"):
        gunzip(data[: len(data) // 2], 1000, "f.gz")
    flipped = bytearray(data)
    flipped[len(data) // 2] ^= 0x10
    with pytest.raises(FileRefused, match="is damaged"):
        gunzip(bytes(flipped), 1000, "f.gz")
    with pytest.raises(FileRefused, match="has data after"):
        gunzip(data + data, 2000, "f.gz")


def test_yaml_aliases_in_a_run_config_are_refused_before_they_expand():
    """Three levels of ten aliases stand for a thousand strings here; nine for a billion."""
    from armeta_rl.run_files import FileRefused, plain_yaml

    text = ('a0: &a0 ["lol","lol","lol","lol","lol","lol","lol","lol","lol","lol"]\n'
            "a1: &a1 [*a0,*a0,*a0,*a0,*a0,*a0,*a0,*a0,*a0,*a0]\nseed: [*a1,*a1]\n")
    with pytest.raises(FileRefused, match="uses YAML anchors or aliases"):
        plain_yaml(text, "config.yaml")
    with pytest.raises(ConfigError, match="its config.yaml uses YAML anchors or aliases"):
        read_run_config(text, "resume", "runs/x")


def test_a_spline_flow_beyond_this_machines_memory_is_refused_before_it_is_built():
    """Ten million layers, or a coupling a million units wide: the spline's parameters (with
    their gradients and Adam's moments) count in the bound, as the planar flow's samples do."""
    with pytest.raises(Refused, match=r"'risk.ar.flow_kwargs.layers' = 10000000: needs at "
                                      r"least .* and its parameters"):
        check_jobs(["+risk.ar.flow_kwargs.layers=10000000"])
    with pytest.raises(Refused, match=r"'risk.ar.flow_kwargs' = \{'hidden': 1000000\}: one "
                                      "spline layer's parameters need"):
        check_jobs(["+risk.ar.flow_kwargs.hidden=1000000"])


@pytest.mark.parametrize("dim", [1, 2, 3, 5])
def test_the_spline_bound_counts_the_parameters_of_the_flows_smaller_layer(dim):
    from armeta_rl.adversary import SplineBoxFlow
    from armeta_rl.resources import spline_layer_parameters
    from armeta_rl.tasks import TaskSpace

    space = TaskSpace([f"x{i}" for i in range(dim)], low=[0] * dim, high=[1] * dim)
    flow = SplineBoxFlow(space, layers=2, bins=5, hidden=7, blocks=3)
    sizes = [sum(p.numel() for p in layer.parameters()) for layer in flow.layers]
    assert spline_layer_parameters(dim, 5, 7, 3) == min(sizes)


@pytest.mark.parametrize("value,words", [
    ("inf", "'benchmark.collector.max_steps' = inf: must be a whole number"),
    ("1000000000000", "'benchmark.collector.max_steps' = 1000000000000: a task's"),
])
def test_an_episode_too_long_for_any_memory_is_refused_against_its_own_key(value, words):
    with pytest.raises(Refused, match=words):
        check_jobs(["benchmark=point_nav", f"benchmark.collector.max_steps={value}"])


def test_a_path_component_the_file_system_cannot_hold_is_one_line(tmp_path, capsys):
    line = refusal(train, [f"resume={tmp_path / ('x' * 300)}"], capsys)
    assert "its config.yaml cannot be read (File name too long)" in line


@pytest.mark.parametrize("override,words", [
    ("hydra.launcher.n_jobs=abc", "'hydra.launcher.n_jobs' = 'abc': Key 'n_jobs' not in"),
    ("hydra/launcher=nope", "'hydra/launcher' = 'nope': allowed: basic, joblib"),
])
def test_hydras_own_refusals_are_one_line_naming_key_and_value(tmp_path, capsys, override,
                                                                words):
    line = refusal(train, ["-m", "trainer.iterations=1", override,
                           f"hydra.sweep.dir={tmp_path}"], capsys)
    assert words in line


def test_a_write_the_file_size_limit_stops_names_its_file(tmp_path):
    """Under ``ulimit -f`` a write fails with EFBIG (Python ignores SIGXFSZ): the error names
    the file being written, not its hidden staging sibling."""
    path = tmp_path / "table1.md"
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.setrlimit(resource.RLIMIT_FSIZE, (4096, hard))
    try:
        with pytest.raises(OSError) as failed:
            write_text_atomically(path, "x" * 10000)
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
    assert failed.value.filename == str(path) and not list(tmp_path.iterdir())


def test_a_fallback_to_the_previous_checkpoint_is_said_on_stderr(run_dir, capsys):
    state_pt = run_dir / LEADER / "state.pt"
    data = bytearray(state_pt.read_bytes())
    data[len(data) // 2] ^= 0xFF
    state_pt.write_bytes(bytes(data))
    code, _, err = in_process(train, [f"resume={run_dir}"], capsys)
    assert code == 0
    assert "checkpoint-000000000004 is broken (components/0000-leader/state.pt does not " \
           "match its SHA-256): moved to checkpoint-000000000004.broken" in err


def test_a_stop_request_during_the_final_evaluation_is_acknowledged(tmp_path, capsys,
                                                                     monkeypatch):
    from armeta_rl.preemption import StopRequest

    stop, evaluate_players = StopRequest(), training.evaluate_players

    def interrupted(*args, **kwargs):
        stop.request(signal.SIGTERM)
        return evaluate_players(*args, **kwargs)

    monkeypatch.setattr(training, "evaluate_players", interrupted)
    run_training(Job(train_config(*RUN), tmp_path / "run"), progress=False, stop=stop)
    assert (tmp_path / "run" / "eval.json").is_file()
    assert ("SIGTERM arrived during the final evaluation: the run finished first (eval.json "
            "written)") in capsys.readouterr().out
