"""The fault campaign: preemption signals, damaged artefacts, bad inputs and resume
keys, each case run through the command-line tools exactly as a user types it, on this checkout
and on an earlier revision (``--before``), written as a table into docs/failures.md (the
``fault_campaign`` section) and its raw outcomes into ``studies/fault_campaign.json``.

    OMP_NUM_THREADS=1 python studies/fault_campaign.py [--before REV] [--rerun-before]
        [--only CASE,...]

An earlier revision is extracted with ``git archive`` into a temporary directory and its cases run
with that tree first on ``PYTHONPATH`` (its code and configs, this environment's packages); its
outcomes are kept in the JSON file, so later invocations re-run only this checkout's column
(``--rerun-before`` runs both). Every case runs in a fresh temporary directory; a case whose
command could allocate far beyond this machine's memory runs under an address-space limit.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import shutil
import signal
import subprocess
import sys
import tarfile
import tempfile
import time
from collections.abc import Callable
from io import BytesIO
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from timing import DOCS, markdown_table, write_section  # noqa: E402 (the benchmarks' writer)

ROOT = Path(__file__).resolve().parents[1]
RESULTS = Path(__file__).with_name("fault_campaign.json")
PAGE = DOCS / "failures.md"
TOOLS = {
    "armeta-train": "from armeta_rl.cli import train; train()",
    "armeta-eval": "from armeta_rl.cli import evaluate; evaluate()",
    "armeta-reproduce": "from armeta_rl.reproduce.cli import main; main()",
}
TINY = ("trainer.iterations=6", "trainer.checkpoint_every=2", "trainer.log_every=1",
        "trainer.progress=false", "eval.n_tasks=20", "trainer.density_every=2", "logger=csv")
"""A six-iteration AR-MAML run on Sinusoid-U: checkpoints and density frames at 2, 4, 6."""
LONG = ("trainer.iterations=400", "trainer.checkpoint_every=100", "trainer.log_every=10",
        "trainer.progress=false", "eval.n_tasks=20", "trainer.density_every=0", "logger=csv")
"""A run long enough (tens of seconds) to be signalled after its first checkpoint."""
REPRODUCE = ("table1", "profile=tiny", "benchmarks=sinusoid_uniform", "seeds=0")
TEMPORARY = re.compile(r"/tmp/fault_campaign_\w+/")
"""The temporary directory of a campaign, left out of the table."""
CRASH = re.compile(r"traceback|segfault|killed by SIG(TERM|USR1|INT)")
"""An outcome a user meets as a crash: a traceback, a segfault, a catchable signal's death."""
ADDRESS_SPACE = 16 * 2**30
"""The address-space limit of the cases that ask for huge sizes: a command that allocates without
checking fails inside it instead of taking the shared machine's memory."""


class Tree:
    """The code a column runs: a directory first on ``PYTHONPATH``."""

    def __init__(self, path: Path, label: str) -> None:
        self.path, self.label = path, label

    def env(self) -> dict[str, str]:
        env = dict(os.environ, PYTHONPATH=str(self.path), OMP_NUM_THREADS="1",
                   WANDB_MODE="offline", WANDB_SILENT="true", RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER="0",
                   HYDRA_FULL_ERROR="0")
        return env

    def start(self, tool: str, *args: str, cwd: Path, limit: int = 0) -> subprocess.Popen:
        """Start ``tool`` (under an address-space limit of ``limit`` bytes, if any); its output
        goes to files (a pipe would stay open as long as any process it started lives, e.g. a
        sweep's workers)."""
        preexec = (lambda: resource.setrlimit(resource.RLIMIT_AS, (limit,) * 2)
                   ) if limit else None
        out, err = (tempfile.TemporaryFile("w+", errors="replace")  # noqa: SIM115 (closed
                    for _ in range(2))                                # by Result.wait)
        process = subprocess.Popen([sys.executable, "-c", TOOLS[tool], *args], cwd=cwd,
                                   env=self.env(), stdout=out, stderr=err,
                                   preexec_fn=preexec, start_new_session=True)
        process.output = (out, err)
        return process

    def run(self, tool: str, *args: str, cwd: Path, timeout: float = 600,
            limit: int = 0) -> Result:
        process = self.start(tool, *args, cwd=cwd, limit=limit)
        return Result.wait(process, timeout)


def wait_for(ready: Callable[[], bool], process: subprocess.Popen, seconds: float,
             poll: float) -> None:
    """Poll ``ready`` every ``poll`` seconds until it holds, ``process`` ends or ``seconds``
    pass (the case then goes on and reports what it finds)."""
    deadline = time.monotonic() + seconds
    while not ready() and process.poll() is None and time.monotonic() <= deadline:
        time.sleep(poll)


class Result:
    """A finished command: exit code, stdout, stderr, seconds."""

    def __init__(self, code: int, out: str, err: str, seconds: float) -> None:
        self.code, self.out, self.err, self.seconds = code, out, err, seconds

    @classmethod
    def wait(cls, process: subprocess.Popen, timeout: float = 600) -> Result:
        start = time.monotonic()
        note = ""
        try:
            process.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
            note = f"\n(timed out after {timeout:.0f} s)"
        texts = []
        for file in process.output:
            file.seek(0)
            texts.append(file.read())
            file.close()
        return cls(process.returncode, texts[0], texts[1] + note, time.monotonic() - start)

    def lines(self) -> list[str]:
        return [line for line in self.err.strip().splitlines() if line.strip()]

    def describe(self) -> str:
        """How the command ended: a signal, a traceback, or its lines of error output."""
        lines = self.lines()
        if self.code < 0:
            name = signal.Signals(-self.code).name
            what = "segfault" if name == "SIGSEGV" else f"killed by {name}"
            text = f"{what}, {'no message' if not lines else f'{len(lines)} lines'}"
        elif any(line.startswith("Traceback") for line in lines):
            text = f"traceback ({len(lines)} lines), exit {self.code}"
            if "BlockingIOError" in lines[1 if len(lines) > 1 else 0] or (
                    "BlockingIOError" in self.err.split("Traceback")[1]):
                text += ", starting with a chained BlockingIOError"
        elif self.code == 0:
            text = "exit 0" + ("" if not lines else f", {len(lines)} lines on stderr")
        elif len(lines) == 1:
            text = f"one line, exit {self.code}: `{shorten(lines[0])}`"
        else:
            text = f"{len(lines)} lines, exit {self.code}"
        return text


def shorten(line: str, most: int = 160) -> str:
    line = line.replace("|", "\\|").replace("`", "'")
    return line if len(line) <= most else line[: most - 1] + "…"


def eval_rows(run_dir: Path) -> int:
    """Rows of the run's ``eval/initial/mean`` CSV log."""
    path = run_dir / "logs" / "scalars" / "eval" / "initial" / "mean.csv"
    return len(path.read_text().splitlines()) if path.is_file() else 0


def newest_checkpoint(run_dir: Path) -> str:
    found = sorted(p.name for p in (run_dir / "checkpoints").glob("checkpoint-*")
                   if not p.name.endswith(".broken"))
    return found[-1].removeprefix("checkpoint-").lstrip("0") or "0" if found else "none"


class Campaign:
    """The cases, run against ``tree`` in ``work``; reference runs are made once, on demand."""

    def __init__(self, tree: Tree, work: Path) -> None:
        self.tree, self.work = tree, work
        self._made: dict[str, Path] = {}

    def fresh(self, name: str) -> Path:
        path = self.work / name
        shutil.rmtree(path, ignore_errors=True)
        path.mkdir(parents=True)
        return path

    def made(self, name: str, make: Callable[[Path], None]) -> Path:
        """A reference directory made once by ``make`` (then copied by the cases that damage
        it)."""
        if name not in self._made:
            path = self.fresh(f"ref_{name}")
            make(path)
            self._made[name] = path
        return self._made[name]

    def copy(self, name: str, make: Callable[[Path], None], to: str) -> Path:
        source = self.made(name, make)
        target = self.work / to
        shutil.rmtree(target, ignore_errors=True)
        shutil.copytree(source, target, symlinks=True)
        return target

    def train(self, *args: str, cwd: Path | None = None, **kwargs) -> Result:
        return self.tree.run("armeta-train", *args, cwd=cwd or self.work, **kwargs)

    # reference runs ---------------------------------------------------------------------------

    def _whole_tiny(self, path: Path) -> None:
        self._ok(self.train(*TINY, f"hydra.run.dir={path / 'run'}"))

    def _stopped_tiny(self, path: Path) -> None:
        self._ok(self.train(*TINY, "trainer.stop_at=4", f"hydra.run.dir={path / 'run'}"))

    def _whole_long(self, path: Path) -> None:
        self._ok(self.train(*LONG, f"hydra.run.dir={path / 'run'}"))

    def _reproduced(self, path: Path) -> None:
        result = self.tree.run("armeta-reproduce", *REPRODUCE, "launcher=basic",
                               f"results={path / 'results'}", cwd=path)
        if result.code not in (0, 1):
            raise RuntimeError(f"the reference sweep failed:\n{result.err[-3000:]}")

    @staticmethod
    def _ok(result: Result) -> None:
        if result.code != 0:
            raise RuntimeError(f"a reference run failed:\n{result.err[-3000:]}")

    def whole_tiny(self) -> Path:
        return self.made("whole_tiny", self._whole_tiny) / "run"

    def stopped_tiny(self, to: str) -> Path:
        return self.copy("stopped_tiny", self._stopped_tiny, to) / "run"

    def finished_tiny(self, to: str) -> Path:
        return self.copy("whole_tiny", self._whole_tiny, to) / "run"

    def reproduced(self, to: str) -> Path:
        return self.copy("reproduced", self._reproduced, to) / "results"

    def same_eval(self, run_dir: Path, reference: Path) -> str:
        if not (run_dir / "eval.json").is_file():
            return "no eval.json"
        same = (run_dir / "eval.json").read_bytes() == (reference / "eval.json").read_bytes()
        return "eval.json bit-identical to the uninterrupted run's" if same else \
            "eval.json DIFFERS from the uninterrupted run's"

    # preemption -------------------------------------------------------------------------------

    def signalled(self, sig: signal.Signals) -> str:
        run_dir = self.fresh(f"signal_{sig.name}") / "run"
        process = self.tree.start("armeta-train", *LONG, f"hydra.run.dir={run_dir}",
                                  cwd=self.work)
        wait_for(lambda: any(run_dir.glob("checkpoints/checkpoint-*")), process, 300, 0.05)
        time.sleep(1.0)  # into the iterations after the first checkpoint
        process.send_signal(sig)
        result = Result.wait(process, 300)
        kept = newest_checkpoint(run_dir)
        resumed = self.train(f"resume={run_dir}")
        reference = self.made("whole_long", self._whole_long) / "run"
        return (f"{result.describe()}; newest checkpoint: iteration {kept}; resume: exit "
                f"{resumed.code}, {self.same_eval(run_dir, reference)}")

    def case_sigterm(self) -> str:
        return self.signalled(signal.SIGTERM)

    def case_sigusr1(self) -> str:
        return self.signalled(signal.SIGUSR1)

    def case_sigint(self) -> str:
        return self.signalled(signal.SIGINT)

    def parent_killed(self, sig: signal.Signals) -> str:
        home = self.fresh(f"reproduce_{sig.name}")
        results = home / "results"
        process = self.tree.start("armeta-reproduce", *REPRODUCE, "launcher=local", "jobs=2",
                                  "+train.trainer.iterations=20000", f"results={results}",
                                  cwd=home)
        wait_for(lambda: len(list(results.glob("runs/*/*/*/config.yaml"))) >= 2, process, 300, 0.1)
        time.sleep(2.0)
        workers = descendants(process.pid)
        process.send_signal(sig)
        result = Result.wait(process, 300)
        time.sleep(30)
        alive = [pid for pid in workers if running(pid)]
        for pid in alive:
            os.kill(pid, signal.SIGKILL)
        checkpoints = len(list(results.glob("runs/*/*/*/checkpoints/checkpoint-*")))
        return (f"parent: {result.describe()}; {len(alive)} of {len(workers)} worker processes "
                f"still running 30 s later; {checkpoints} checkpoints written")

    def case_reproduce_parent_sigterm(self) -> str:
        return self.parent_killed(signal.SIGTERM)

    def case_reproduce_parent_sigkill(self) -> str:
        return self.parent_killed(signal.SIGKILL)

    # damaged artefacts and finished runs ------------------------------------------------------

    def case_zero_byte_frame(self) -> str:
        run_dir = self.stopped_tiny("zero_frame")
        (run_dir / "density" / "iter_000002.png").write_bytes(b"")
        result = self.train(f"resume={run_dir}")
        gif = (run_dir / "density.gif").is_file()
        return (f"resume: {result.describe()}; density.gif {'written' if gif else 'missing'}; "
                f"{self.same_eval(run_dir, self.whole_tiny())}")

    def case_resume_finished(self) -> str:
        run_dir = self.finished_tiny("refinished")
        before = (run_dir / "eval.json").read_bytes()
        result = self.train(f"resume={run_dir}")
        same = (run_dir / "eval.json").read_bytes() == before
        return (f"{result.describe()}; {eval_rows(run_dir)} row(s) in eval/initial/mean.csv; "
                f"eval.json {'unchanged' if same else 'rewritten with other values'}")

    def case_all_checkpoints_broken(self) -> str:
        run_dir = self.stopped_tiny("all_broken")
        for state in run_dir.glob("checkpoints/*/components/0000-leader/state.pt"):
            data = bytearray(state.read_bytes())
            data[len(data) // 2] ^= 0xFF
            state.write_bytes(bytes(data))
        first = self.train(f"resume={run_dir}")
        second = self.train(f"resume={run_dir}")
        retrained = (run_dir / "eval.json").is_file()
        return (f"first resume: {first.describe()}; the same command again: "
                f"{second.describe()}" + ("; it retrained from iteration 0" if retrained else ""))

    # bad input --------------------------------------------------------------------------------

    def case_hydra_run_dir_empty(self) -> str:
        cwd = self.fresh("empty_run_dir")
        (cwd / "logs").mkdir()
        (cwd / "logs" / "mine.txt").write_text("a user's file\n")
        result = self.train(*TINY, "hydra.run.dir=", cwd=cwd)
        written = sorted(p.name for p in cwd.iterdir() if p.name != "logs")
        merged = sorted(p.name for p in (cwd / "logs").iterdir() if p.name != "mine.txt")
        return (f"{result.describe()}" + (f"; wrote {', '.join(written)} into the current "
                                          f"directory" if written else "")
                + (f" and {', '.join(merged)} into its logs/" if merged else ""))

    def damaged_config(self, how: str, tool: str) -> str:
        run_dir = self.finished_tiny(f"config_{how}_{tool}")
        config = run_dir / "config.yaml"
        config.write_text("" if how == "empty" else config.read_text()[:300])
        if tool == "armeta-train":
            (run_dir / "eval.json").unlink()
            result = self.train(f"resume={run_dir}")
        else:
            result = self.tree.run("armeta-eval", f"learner={run_dir}",
                                   f"out={run_dir / 'again.json'}", cwd=self.work)
        return result.describe()

    def case_empty_config_resume(self) -> str:
        return self.damaged_config("empty", "armeta-train")

    def case_truncated_config_resume(self) -> str:
        return self.damaged_config("truncated", "armeta-train")

    def case_empty_config_eval(self) -> str:
        return self.damaged_config("empty", "armeta-eval")

    def case_truncated_config_eval(self) -> str:
        return self.damaged_config("truncated", "armeta-eval")

    def reproduce_again(self, results: Path, *args: str) -> Result:
        return self.tree.run("armeta-reproduce", *REPRODUCE, *args, f"results={results}",
                             cwd=results.parent)

    def case_empty_config_reproduce(self) -> str:
        results = self.reproduced("config_reproduce")
        run_dir = results / "runs" / "sinusoid_uniform" / "maml" / "seed0"
        (run_dir / "eval.json").unlink()
        (run_dir / "config.yaml").write_text("")
        return self.reproduce_again(results, "launcher=basic").describe()

    def case_threads_huge(self) -> str:
        run_dir = self.fresh("threads") / "run"
        return self.train(*TINY, "threads=100000", f"hydra.run.dir={run_dir}").describe()

    def huge(self, name: str, override: str) -> str:
        run_dir = self.fresh(name) / "run"
        result = self.train(*TINY, override, f"hydra.run.dir={run_dir}", limit=ADDRESS_SPACE)
        return f"{result.describe()} after {result.seconds:.0f} s"

    def case_eval_n_tasks_huge(self) -> str:
        return self.huge("n_tasks", "eval.n_tasks=100000000")

    def case_meta_batch_huge(self) -> str:
        return self.huge("meta_batch", "trainer.meta_batch=100000000")

    def case_initial_samples_huge(self) -> str:
        return self.huge("initial_samples", "risk.ar.initial_samples=1000000000000")

    def case_space_high_huge(self) -> str:
        run_dir = self.fresh("space_high") / "run"
        return self.train(*TINY, "benchmark.space.high=[1e300,3.14]",
                          f"hydra.run.dir={run_dir}").describe()

    def case_normal_p0_outside(self) -> str:
        run_dir = self.fresh("p0_outside") / "run"
        return self.train(*TINY, "benchmark=sinusoid_normal", "benchmark.initial.loc=[40,40]",
                          f"hydra.run.dir={run_dir}").describe()

    def case_reproduce_results_file(self) -> str:
        home = self.fresh("results_file")
        (home / "a_file").write_text("")
        return self.reproduce_again(home / "a_file", "launcher=basic").describe()

    def case_reproduce_results_read_only(self) -> str:
        home = self.fresh("results_read_only")
        return self.tree.run("armeta-reproduce", *REPRODUCE, "launcher=basic",
                             "results=/proc/armeta-results", cwd=home).describe()

    def case_reproduce_garbled_manifest(self) -> str:
        results = self.reproduced("garbled_manifest")
        (results / "reproduce.yaml").write_text("experiment: [table1\nprofile: {\n")
        return self.reproduce_again(results, "launcher=none").describe()

    def damaged_report(self, name: str, damage: Callable[[Path], None]) -> str:
        results = self.reproduced(name)
        run_dir = results / "runs" / "sinusoid_uniform" / "maml" / "seed0"
        damage(run_dir)
        result = self.reproduce_again(results, "launcher=none")
        table = results / "table1.csv"
        rows = [row for row in (table.read_text().splitlines() if table.is_file() else [])
                if row.startswith("sinusoid_uniform,maml,,0,initial,False,")]
        shown = (f"aggregated with mean {rows[0].split(',')[7]}" if rows
                 else "left out of table1.csv")
        note = re.search(r"(\d+/\d+) training runs", (results / "table1.md").read_text()
                         ) if (results / "table1.md").is_file() else None
        return (f"{result.describe()}; the run is {shown}; the report counts "
                f"{note.group(1) if note else '?'} training runs finished")

    def case_reproduce_empty_eval_report(self) -> str:
        return self.damaged_report("empty_report", lambda run: next(
            run.glob("eval_vs_*.json")).write_bytes(b""))

    def case_reproduce_non_utf8_eval_report(self) -> str:
        return self.damaged_report("non_utf8_report", lambda run: next(
            run.glob("eval_vs_*.json")).write_bytes(b"\xff\xfe{\x00\x93"))

    @staticmethod
    def edit_eval(run_dir: Path, edit: Callable[[dict], None]) -> None:
        path = run_dir / "eval.json"
        report = json.loads(path.read_text())
        edit(report)
        path.write_text(json.dumps(report, indent=2))

    def case_eval_json_mean_12345(self) -> str:
        return self.damaged_report("mean_12345", lambda run: self.edit_eval(
            run, lambda r: r["initial"].update(mean=12345)))

    def case_eval_json_nan(self) -> str:
        return self.damaged_report("mean_nan", lambda run: self.edit_eval(
            run, lambda r: r["initial"].update(mean=float("nan"))))

    def case_eval_json_no_initial(self) -> str:
        return self.damaged_report("no_initial", lambda run: self.edit_eval(
            run, lambda r: r.pop("initial")))

    def case_reproduce_ray_address(self) -> str:
        home = self.fresh("ray_address")
        result = self.tree.run("armeta-reproduce", *REPRODUCE, "launcher=ray",
                               "hydra.launcher.ray.init.address=127.0.0.1:1",
                               f"results={home / 'results'}", cwd=home, timeout=300)
        return f"{result.describe()} after {result.seconds:.0f} s"

    def case_eval_nonexistent_learner(self) -> str:
        return self.tree.run("armeta-eval", "learner=/nonexistent/run", cwd=self.work).describe()

    def case_eval_unwritable_out(self) -> str:
        run_dir = self.finished_tiny("unwritable_out")
        result = self.tree.run("armeta-eval", f"learner={run_dir}",
                               "out=/proc/armeta-eval.json", cwd=self.work)
        evaluated = result.code not in (0, 2)  # the write failed after the evaluation
        return (f"{result.describe()}; " + ("refused after evaluating" if evaluated
                                             else "refused before evaluating"))

    # resume keys that change no result --------------------------------------------------------

    def resumed_with(self, name: str, override: str) -> str:
        run_dir = self.stopped_tiny(name)
        result = self.train(f"resume={run_dir}", override)
        text = result.describe()
        if result.code == 0:
            text += f"; {self.same_eval(run_dir, self.whole_tiny())}"
        return text

    def case_resume_logger_wandb(self) -> str:
        return self.resumed_with("resume_wandb", "logger=wandb")

    def case_resume_progress(self) -> str:
        return self.resumed_with("resume_progress", "trainer.progress=true")

    def case_resume_threads(self) -> str:
        return self.resumed_with("resume_threads", "threads=2")

    def case_resume_log_every(self) -> str:
        return self.resumed_with("resume_log_every", "trainer.log_every=3")

    def case_resume_density_every(self) -> str:
        return self.resumed_with("resume_density_every", "trainer.density_every=3")

    # the run directory as a trust boundary ---------------------------------------------------

    def case_checkpoint_other_seed(self) -> str:
        run_dir = self.stopped_tiny("other_seed")
        other = self.fresh("other_seed_4") / "run"
        self._ok(self.train(*TINY, "seed=4", "trainer.stop_at=4", f"hydra.run.dir={other}"))
        shutil.rmtree(run_dir / "checkpoints")
        shutil.copytree(other / "checkpoints", run_dir / "checkpoints")
        result = self.train(f"resume={run_dir}")
        written = (run_dir / "eval.json").is_file()
        return f"{result.describe()}; {'wrote' if written else 'no'} eval.json under seed 0"

    def case_eval_json_other_method(self) -> str:
        return self.damaged_report("other_method", lambda run: shutil.copy(
            run.parent.parent / "dr_maml" / "seed0" / "eval.json", run / "eval.json"))

    def case_eval_json_initial_str(self) -> str:
        return self.damaged_report("initial_str", lambda run: self.edit_eval(
            run, lambda r: r.update(initial="str")))

    def case_eval_json_dev_zero(self) -> str:
        results = self.reproduced("dev_zero")
        report = results / "runs" / "sinusoid_uniform" / "maml" / "seed0" / "eval.json"
        report.unlink()
        report.symlink_to("/dev/zero")
        return self.tree.run("armeta-reproduce", *REPRODUCE, "launcher=none",
                             f"results={results}", cwd=self.work, limit=2 * 2**30,
                             timeout=120).describe()

    def case_lock_symlink(self) -> str:
        run_dir = self.stopped_tiny("lock_symlink")
        target = self.work / "lock_target.txt"
        target.write_text("keep me\n")
        (run_dir / "run.lock").unlink(missing_ok=True)
        (run_dir / "run.lock").symlink_to(target)
        result = self.train(f"resume={run_dir}")
        kept = target.read_text() == "keep me\n" and (run_dir / "run.lock").is_symlink()
        return (f"{result.describe()}; the link's target "
                f"{'untouched' if kept else 'WRITTEN or the link removed'}")

    def odd_run_dir(self, name: str, make: Callable[[Path], Path]) -> str:
        return self.train(*TINY, f"hydra.run.dir={make(self.fresh(name))}").describe()

    def case_run_dir_dangling_link(self) -> str:
        def make(home: Path) -> Path:
            (home / "run").symlink_to(home / "nowhere")
            return home / "run"
        return self.odd_run_dir("dangling", make)

    def case_run_dir_link_loop(self) -> str:
        def make(home: Path) -> Path:
            (home / "run").symlink_to(home / "run")
            return home / "run"
        return self.odd_run_dir("loop", make)

    def case_run_dir_long_component(self) -> str:
        return self.odd_run_dir("long", lambda home: home / ("x" * 300))

    def case_ar_lr_huge(self) -> str:
        run_dir = self.fresh("lr_huge") / "run"
        return self.train(*TINY, "risk.ar.lr=1e30", f"hydra.run.dir={run_dir}").describe()

    def bounded(self, name: str, override: str) -> str:
        run_dir = self.fresh(name) / "run"
        result = self.train(*TINY, override, f"hydra.run.dir={run_dir}", limit=4 * 2**30,
                            timeout=120)
        return f"{result.describe()} after {result.seconds:.0f} s"

    def case_inner_steps_huge(self) -> str:
        return self.bounded("inner_steps", "learner.maml.inner_steps=1000000")

    def case_flow_layers_huge(self) -> str:
        return self.bounded("flow_layers", "+risk.ar.flow_kwargs.layers=100000000")

    def case_hidden_huge(self) -> str:
        return self.bounded("hidden", "learner.maml.hidden=[1000000,1000000]")

    def case_eval_out_fifo(self) -> str:
        run_dir = self.finished_tiny("out_fifo")
        fifo = self.work / "out.fifo"
        os.mkfifo(fifo)
        result = self.tree.run("armeta-eval", f"learner={run_dir}", f"out={fifo}",
                               cwd=self.work, timeout=300)
        return f"{result.describe()}; out {'still a pipe' if fifo.is_fifo() else 'REPLACED'}"

    def case_resume_other_run_dir(self) -> str:
        run_dir = self.stopped_tiny("other_run_dir")
        elsewhere = self.work / "elsewhere"
        result = self.train(f"resume={run_dir}", f"hydra.run.dir={elsewhere}")
        where = "elsewhere" if (elsewhere / "armeta-train.log").is_file() else "the run's own"
        return f"{result.describe()}; the job log in {where} directory"

    def case_checkpoints_a_file(self) -> str:
        run_dir = self.stopped_tiny("checkpoints_file")
        shutil.rmtree(run_dir / "checkpoints")
        (run_dir / "checkpoints").write_text("not a directory\n")
        result = self.train(f"resume={run_dir}")
        trained = eval_rows(run_dir) if (run_dir / "logs").is_dir() else 0
        return f"{result.describe()}; {trained} row(s) in eval/initial/mean.csv"

    def case_frame_cut_off(self) -> str:
        run_dir = self.stopped_tiny("frame_cut_off")
        for name in ("iter_000004.png", "iter_000004.pt"):
            (run_dir / "density" / name).unlink(missing_ok=True)
        result = self.train(f"resume={run_dir}")
        same = (run_dir / "density.gif").read_bytes() == (
            self.whole_tiny() / "density.gif").read_bytes()
        return (f"{result.describe()}; density.gif "
                f"{'equal to' if same else 'DIFFERS from'} the uninterrupted run's")


CASES = {
    "sigterm": "SIGTERM to `armeta-train` after its first checkpoint (100 of 400 iterations)",
    "sigusr1": "SIGUSR1, likewise",
    "sigint": "SIGINT (Ctrl-C), likewise",
    "reproduce_parent_sigterm": "SIGTERM to the parent `armeta-reproduce launcher=local jobs=2`",
    "reproduce_parent_sigkill": "SIGKILL to the parent `armeta-reproduce launcher=local jobs=2`",
    "zero_byte_frame": "a 0-byte `density/iter_000002.png`, then `resume=`",
    "resume_finished": "`resume=` a finished run",
    "all_checkpoints_broken": "every checkpoint broken: `resume=`, then the same command again",
    "hydra_run_dir_empty": "`hydra.run.dir=` (empty), in a directory with a `logs/`",
    "empty_config_resume": "empty `config.yaml`: `resume=`",
    "truncated_config_resume": "truncated `config.yaml`: `resume=`",
    "empty_config_eval": "empty `config.yaml`: `armeta-eval learner=`",
    "truncated_config_eval": "truncated `config.yaml`: `armeta-eval learner=`",
    "empty_config_reproduce": "empty `config.yaml` of an unfinished run: `armeta-reproduce`",
    "threads_huge": "`threads=100000`",
    "eval_n_tasks_huge": "`eval.n_tasks=100000000`",
    "meta_batch_huge": "`trainer.meta_batch=100000000`",
    "initial_samples_huge": "`risk.ar.initial_samples=1000000000000`",
    "space_high_huge": "`benchmark.space.high=[1e300,3.14]`",
    "normal_p0_outside": "`benchmark=sinusoid_normal benchmark.initial.loc=[40,40]` (p0 centred "
                         "outside the box)",
    "reproduce_results_file": "`armeta-reproduce results=` a file",
    "reproduce_results_read_only": "`armeta-reproduce results=/proc/armeta-results` (read-only)",
    "reproduce_garbled_manifest": "a garbled `reproduce.yaml`",
    "reproduce_empty_eval_report": "an empty `eval_vs_*.json`: `armeta-reproduce launcher=none`",
    "reproduce_non_utf8_eval_report": "a non-UTF-8 `eval_vs_*.json`, likewise",
    "eval_json_mean_12345": "`eval.json` edited to `\"mean\": 12345`, likewise",
    "eval_json_nan": "`eval.json` edited to `\"mean\": NaN`, likewise",
    "eval_json_no_initial": "`eval.json` without `\"initial\"`, likewise",
    "reproduce_ray_address": "`armeta-reproduce launcher=ray "
                             "hydra.launcher.ray.init.address=127.0.0.1:1` (nothing listens)",
    "eval_nonexistent_learner": "`armeta-eval learner=/nonexistent/run`",
    "eval_unwritable_out": "`armeta-eval out=/proc/armeta-eval.json` (cannot be written)",
    "resume_logger_wandb": "`resume=` with `logger=wandb` (the run logged to CSV)",
    "resume_progress": "`resume=` with `trainer.progress=true`",
    "resume_threads": "`resume=` with `threads=2` (the run had 1)",
    "resume_log_every": "`resume=` with `trainer.log_every=3`",
    "resume_density_every": "`resume=` with `trainer.density_every=3`",
    "checkpoint_other_seed": "a seed-4 run's checkpoints copied into a seed-0 run: `resume=`",
    "eval_json_other_method": "`dr_maml`'s `eval.json` copied into `maml/seed0`: "
                              "`armeta-reproduce launcher=none`",
    "eval_json_initial_str": "`eval.json` edited to `\"initial\": \"str\"`, likewise",
    "eval_json_dev_zero": "`eval.json` a link to `/dev/zero`, likewise",
    "lock_symlink": "`run.lock` a link to another file: `resume=`",
    "run_dir_dangling_link": "`hydra.run.dir=` a link to nothing",
    "run_dir_link_loop": "`hydra.run.dir=` a link to itself",
    "run_dir_long_component": "`hydra.run.dir=` with a 300-byte name",
    "ar_lr_huge": "`risk.ar.lr=1e30`",
    "inner_steps_huge": "`learner.maml.inner_steps=1000000` (cut after 120 s)",
    "flow_layers_huge": "`+risk.ar.flow_kwargs.layers=100000000` (cut after 120 s)",
    "hidden_huge": "`learner.maml.hidden=[1000000,1000000]` (cut after 120 s)",
    "eval_out_fifo": "`armeta-eval out=` a named pipe",
    "resume_other_run_dir": "`resume=` with another `hydra.run.dir=`",
    "checkpoints_a_file": "`checkpoints` a file: `resume=`",
    "frame_cut_off": "the density frame (picture and numbers) of the newest checkpoint lost, "
                     "as a kill just after the checkpoint leaves it: `resume=`",
}


def descendants(pid: int) -> list[int]:
    """Every process below ``pid`` (Linux ``/proc``)."""
    children: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        children.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    found, todo = [], [pid]
    while todo:
        for child in children.get(todo.pop(), []):
            found.append(child)
            todo.append(child)
    return found


def running(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def extract(revision: str, into: Path) -> Path:
    """The tree of ``revision`` of this repository, extracted into ``into``."""
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", revision], check=True,
                             capture_output=True).stdout
    with tarfile.open(fileobj=BytesIO(archive)) as tar:
        tar.extractall(into, filter="data")
    return into


def current_label() -> str:
    head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"],
                          capture_output=True, text=True).stdout.strip()
    dirty = subprocess.run(["git", "-C", str(ROOT), "status", "--porcelain", "--",
                            "armeta_rl", "configs", "hydra_plugins"],
                           capture_output=True, text=True).stdout.strip()
    return head + ("+" if dirty else "")


def run_cases(tree: Tree, names: list[str]) -> dict[str, str]:
    outcomes = {}
    with tempfile.TemporaryDirectory(prefix="fault_campaign_") as work:
        campaign = Campaign(tree, Path(work))
        for name in names:
            start = time.monotonic()
            try:
                outcomes[name] = getattr(campaign, f"case_{name}")()
            except Exception as error:  # a case the campaign itself could not run
                outcomes[name] = f"campaign error: {type(error).__name__}: {error}"[:300]
            print(f"[{tree.label}] {name} ({time.monotonic() - start:.0f} s): "
                  f"{outcomes[name]}", flush=True)
    return outcomes


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--before", default="075b143",
                        help="the revision of the 'before' column")
    parser.add_argument("--rerun-before", action="store_true")
    parser.add_argument("--only", default="", help="comma-separated cases (default: all)")
    parser.add_argument("--skip-now", action="store_true",
                        help="run only the 'before' column")
    args = parser.parse_args()
    names = [n for n in args.only.split(",") if n] or list(CASES)
    stored = json.loads(RESULTS.read_text()) if RESULTS.is_file() else {}
    before = stored.get("before", {})
    if args.rerun_before or before.get("revision") != args.before or not all(
            name in before.get("cases", {}) for name in names):
        with tempfile.TemporaryDirectory(prefix="fault_campaign_tree_") as tree_dir:
            tree = Tree(extract(args.before, Path(tree_dir)), args.before)
            cases = before.get("cases", {}) if before.get("revision") == args.before else {}
            cases.update(run_cases(tree, names))
        before = {"revision": args.before, "cases": cases}
    stored["before"] = before
    if not args.skip_now:
        now = stored.get("now", {"cases": {}})
        label = current_label()
        now["cases"].update(run_cases(Tree(ROOT, label), names))
        now["revision"] = label
        stored["now"] = now
    RESULTS.write_text(json.dumps(stored, indent=1, sort_keys=True) + "\n")
    if "now" in stored:
        columns = [stored[column]["cases"] for column in ("before", "now")]
        rows = [(case, *(TEMPORARY.sub("…/", cases.get(name, "–")) for cases in columns))
                for name, case in CASES.items()]
        table = markdown_table(("case", f"before ({stored['before']['revision']})",
                                f"now ({stored['now']['revision']})"), rows)
        counts = [sum(CRASH.search(cases.get(name, "")) is not None for name in CASES)
                  for cases in columns]
        write_section("fault_campaign", "The fault campaign", (
            "Each case run through the command-line tools as a user types it "
            "(`studies/fault_campaign.py`; raw outcomes in "
            "`studies/fault_campaign.json`; the columns may come from runs of some cases "
            "only, `--only`). Exit codes: 0 done, 1 a failed run or sweep, 2 bad input, 75 "
            "stopped by a preemption signal (resume it), 130 stopped by SIGINT. Cases ending in "
            f"a traceback, a segfault or a death by a catchable signal: {counts[0]} of "
            f"{len(CASES)} before, {counts[1]} now.\n\n" + table), PAGE,
            command=f"OMP_NUM_THREADS=1 python studies/fault_campaign.py --before {args.before}")


if __name__ == "__main__":
    main()
