"""The fault campaign: preemption signals, damaged artefacts, bad inputs, resume keys and
run directories handed over by a hostile colleague, each case run through the command-line tools
exactly as a user types it, on this checkout and on the earlier revision its group of cases was
first run against, written as tables into docs/failures.md (the ``fault_campaign``
section) and its raw outcomes into ``studies/fault_campaign.json``.

    OMP_NUM_THREADS=1 python studies/fault_campaign.py [--rerun-before] [--only CASE,...]

An earlier revision is extracted with ``git archive`` into a temporary directory and its cases run
with that tree first on ``PYTHONPATH`` (its code and configs, this environment's packages); its
outcomes are kept in the JSON file, so later invocations re-run only this checkout's column
(``--rerun-before`` runs both). Every case runs in a fresh temporary directory; a case whose
command could allocate far beyond this machine's memory runs under an address-space limit, and
a case that could wait forever is cut after a time, which its outcome says.
"""

from __future__ import annotations

import argparse
import gzip
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
import zlib
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

    def start(self, tool: str, *args: str, cwd: Path, limit: int = 0,
              file_limit: int = 0) -> subprocess.Popen:
        """Start ``tool`` (under an address-space limit of ``limit`` bytes and a file-size limit
        of ``file_limit`` bytes, ``ulimit -f``, if any); its output goes to files (a pipe would
        stay open as long as any process it started lives, e.g. a sweep's workers)."""
        limits = [(kind, size) for kind, size in ((resource.RLIMIT_AS, limit),
                                                  (resource.RLIMIT_FSIZE, file_limit)) if size]

        def preexec() -> None:
            for kind, size in limits:
                resource.setrlimit(kind, (size, size))

        out, err = (tempfile.TemporaryFile("w+", errors="replace")  # noqa: SIM115 (closed
                    for _ in range(2))                                # by Result.wait)
        process = subprocess.Popen([sys.executable, "-c", TOOLS[tool], *args], cwd=cwd,
                                   env=self.env(), stdout=out, stderr=err,
                                   preexec_fn=preexec if limits else None,
                                   start_new_session=True)
        process.output = (out, err)
        return process

    def run(self, tool: str, *args: str, cwd: Path, timeout: float = 600,
            limit: int = 0, file_limit: int = 0) -> Result:
        process = self.start(tool, *args, cwd=cwd, limit=limit, file_limit=file_limit)
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
        """How the command ended: cut at its time limit (a hang), a signal, a traceback, or its
        lines of error output."""
        lines = self.lines()
        cut = re.search(r"\(timed out after (\d+) s\)", self.err)
        if cut:
            return f"timed out after {cut.group(1)} s (a hang), killed"
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

    def reproduce_again(self, results: Path, *args: str, **limits: float) -> Result:
        return self.tree.run("armeta-reproduce", *REPRODUCE, *args, f"results={results}",
                             cwd=results.parent, **limits)

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


    # a run directory is data, never code (issue 60) ---------------------------------------

    def marked(self, name: str) -> Path:
        """The file a crafted payload's code would create: its existence proves code ran."""
        marker = self.work / "markers" / name
        marker.parent.mkdir(exist_ok=True)
        marker.unlink(missing_ok=True)
        return marker

    @staticmethod
    def ran(marker: Path) -> str:
        return "; CODE RAN (the marker file appeared)" if marker.exists() else "; no code ran"

    @staticmethod
    def newest(run_dir: Path) -> Path:
        return sorted(p for p in (run_dir / "checkpoints").glob("checkpoint-*")
                      if not p.name.endswith(".broken"))[-1]

    @staticmethod
    def resealed(checkpoint: Path, edit: Callable[[dict], None] = lambda manifest: None) -> None:
        """Let ``edit`` change ``checkpoint``'s manifest, then seal it again with the package's
        own ``seal`` (what anyone can do): its digests then match whatever it holds."""
        from armeta_rl.trainers.checkpoint import MANIFEST, seal

        manifest = json.loads((checkpoint / MANIFEST).read_text())
        edit(manifest)
        (checkpoint / MANIFEST).write_text(json.dumps(manifest))
        seal(checkpoint, manifest["metadata"].get("identity"))

    def memmap_payload(self, run_dir: Path, marker: Path) -> None:
        """The newest checkpoint's leader payload as a TensorDict memory map with a pickled
        field whose unpickling creates ``marker``, listed in the manifest and resealed."""
        import tensordict
        import torch

        checkpoint = self.newest(run_dir)
        component = checkpoint / "components" / "0000-leader"
        data = tensordict.TensorDict({"x": torch.zeros(1)}, batch_size=[])
        data.set_non_tensor("payload", Pickled(marker))
        (component / "state.pt").unlink()
        tensordict.save(data, component / "state")
        (component / "state.json").write_text('{"kind":"tensor","key":"x","device":"cpu"}')
        files = sorted(str(p.relative_to(component)) for p in component.rglob("*")
                       if p.is_file())
        self.resealed(checkpoint, lambda m: m["components"]["leader"].update(files=files))

    def global_payload(self, run_dir: Path, marker: Path) -> None:
        """The newest checkpoint's leader ``state.pt`` with an object whose unpickling creates
        ``marker`` (a pickle GLOBAL), resealed."""
        import torch

        state_pt = self.newest(run_dir) / "components" / "0000-leader" / "state.pt"
        state = torch.load(state_pt, weights_only=True)
        state["payload"] = Pickled(marker)
        torch.save(state, state_pt)
        self.resealed(state_pt.parents[2])

    def crafted(self, name: str, craft: str, tool: str) -> str:
        marker = self.marked(name)
        if tool in ("frozen", "adversary"):
            run_dir = self.finished_tiny(name)
        else:
            run_dir = self.stopped_tiny(name)
        (self.memmap_payload if craft == "memmap" else self.global_payload)(run_dir, marker)
        if tool == "resume":
            result = self.train(f"resume={run_dir}")
        elif tool == "eval":
            result = self.tree.run("armeta-eval", f"learner={run_dir}",
                                   f"out={self.work / name / 'out.json'}", cwd=self.work)
        elif tool == "frozen":
            attack = self.fresh(f"{name}_attack") / "run"
            result = self.train(*TINY, f"trainer.frozen_leader={run_dir}",
                                f"hydra.run.dir={attack}")
        else:
            result = self.tree.run("armeta-eval", f"learner={self.whole_tiny()}",
                                   f"adversary={run_dir}",
                                   f"out={self.work / name / 'out.json'}", cwd=self.work)
        return result.describe() + self.ran(marker)

    def case_memmap_pickle_resume(self) -> str:
        return self.crafted("memmap_resume", "memmap", "resume")

    def case_memmap_pickle_eval(self) -> str:
        return self.crafted("memmap_eval", "memmap", "eval")

    def case_memmap_pickle_frozen(self) -> str:
        return self.crafted("memmap_frozen", "memmap", "frozen")

    def case_memmap_pickle_adversary(self) -> str:
        return self.crafted("memmap_adversary", "memmap", "adversary")

    def case_global_payload_resume(self) -> str:
        return self.crafted("global_resume", "global", "resume")

    def case_global_payload_eval(self) -> str:
        return self.crafted("global_eval", "global", "eval")

    def linked_payload(self, name: str, link: Callable[[Path, Path], None]) -> str:
        run_dir = self.stopped_tiny(name)
        state_pt = self.newest(run_dir) / "components" / "0000-leader" / "state.pt"
        outside = self.work / f"{name}_outside.pt"
        outside.unlink(missing_ok=True)
        link(state_pt, outside)
        result = self.train(f"resume={run_dir}")
        followed = result.code == 0
        return result.describe() + ("; HARMFUL: the payload outside the run was read and "
                                    "trained on" if followed else "")

    def case_payload_symlink(self) -> str:
        def link(state_pt: Path, outside: Path) -> None:
            state_pt.rename(outside)
            state_pt.symlink_to(outside)
        return self.linked_payload("payload_symlink", link)

    def case_payload_hardlink(self) -> str:
        return self.linked_payload("payload_hardlink", lambda state_pt, outside: os.link(
            state_pt, outside))

    def case_checkpoint_dir_symlink(self) -> str:
        run_dir = self.stopped_tiny("checkpoint_link")
        newest = self.newest(run_dir)
        outside = self.work / "checkpoint_link_outside"
        shutil.rmtree(outside, ignore_errors=True)
        newest.rename(outside)
        newest.symlink_to(outside)
        result = self.train(f"resume={run_dir}")
        return result.describe() + ("; HARMFUL: the checkpoint outside the run was loaded"
                                    if result.code == 0 else "")

    def unidentified(self, name: str, *extra: str) -> tuple[Result, Path]:
        """A seed-4 run's checkpoints with their identity removed (resealed) in a seed-0 run."""
        run_dir = self.stopped_tiny(name)
        other = self.fresh(f"{name}_seed4") / "run"
        self._ok(self.train(*TINY, "seed=4", "trainer.stop_at=4", f"hydra.run.dir={other}"))
        shutil.rmtree(run_dir / "checkpoints")
        shutil.copytree(other / "checkpoints", run_dir / "checkpoints")
        for checkpoint in (run_dir / "checkpoints").glob("checkpoint-*"):
            self.resealed(checkpoint, lambda m: m["metadata"].pop("identity", None))
        return self.train(f"resume={run_dir}", *extra), run_dir

    def case_checkpoint_no_identity(self) -> str:
        result, run_dir = self.unidentified("no_identity")
        return result.describe() + ("; HARMFUL: trained on the seed-4 checkpoint as seed 0"
                                    if (run_dir / "eval.json").is_file() else "")

    def case_checkpoint_no_identity_adopt(self) -> str:
        result, run_dir = self.unidentified("no_identity_adopt", "adopt=true")
        trained = (run_dir / "eval.json").is_file()
        return result.describe() + ("; trained on it as seed 0, as adopt=true says"
                                    if trained else "")

    def maml_row(self, results: Path) -> str:
        """Whether ``table1.csv`` holds maml seed 0's p0 row (and its mean)."""
        table = results / "table1.csv"
        rows = [row for row in (table.read_text().splitlines() if table.is_file() else [])
                if row.startswith("sinusoid_uniform,maml,,0,initial,False,")]
        return f"aggregated with mean {rows[0].split(',')[7]}" if rows else "left out"

    def relabelled(self, results: Path) -> float:
        """dr_maml seed 0's eval.json in maml/seed0, its seed and digest deleted and its
        method relabelled; dr_maml's p0 mean."""
        runs = results / "runs" / "sinusoid_uniform"
        report = json.loads((runs / "dr_maml" / "seed0" / "eval.json").read_text())
        for name in ("seed", "config_sha256"):
            report.pop(name, None)
        report["method"] = "maml"
        (runs / "maml" / "seed0" / "eval.json").write_text(json.dumps(report, indent=2))
        return report["initial"]["mean"]

    def case_report_identity_removed(self) -> str:
        results = self.reproduced("identity_removed")
        theirs = self.relabelled(results)
        result = self.reproduce_again(results, "launcher=none")
        shown = self.maml_row(results)
        harm = "; HARMFUL: dr_maml's report counted as maml's" if str(theirs) in shown else ""
        return f"{result.describe()}; the run is {shown}{harm}"

    def case_pack_refused_report(self) -> str:
        results = self.reproduced("pack_refused")
        self.relabelled(results)
        result = self.reproduce_again(results, "launcher=none", "pack=true")
        packed = results / "reports.jsonl.gz"
        held = packed.is_file() and any(
            json.loads(line)["run"] == "runs/sinusoid_uniform/maml/seed0"
            and json.loads(line)["file"] == "eval.json"
            for line in gzip.decompress(packed.read_bytes()).decode().splitlines())
        return result.describe() + ("; HARMFUL: the relabelled report was packed" if held
                                    else "; the relabelled report not packed")

    def _noise(self, path: Path) -> None:
        result = self.tree.run("armeta-reproduce", "noise", "profile=tiny", "launcher=basic",
                               f"results={path / 'results'}", cwd=path)
        if result.code != 0:
            raise RuntimeError(f"the noise sweep failed:\n{result.err[-3000:]}")

    def case_other_experiment_run(self) -> str:
        results = self.reproduced("other_experiment_run")
        noise = self.made("noise", self._noise) / "results"
        ours = results / "runs" / "sinusoid_uniform" / "maml" / "seed0"
        shutil.rmtree(ours)
        shutil.copytree(noise / "runs" / "sinusoid_uniform" / "maml" / "seed0", ours)
        result = self.reproduce_again(results, "launcher=none")
        table = (results / "table1.csv").read_text() if (results / "table1.csv").is_file() else ""
        noisy = any(row.startswith("sinusoid_uniform,maml,,0,") and ",True," in row
                    for row in table.splitlines())
        return result.describe() + ("; HARMFUL: the noise run's report aggregated (its noisy "
                                    "rows in table1.csv)" if noisy else
                                    f"; the run is {self.maml_row(results)}")

    def case_other_experiment_packed(self) -> str:
        results = self.fresh("other_experiment_packed") / "results"
        packed = self.made("noise_packed", self._noise_packed) / "results"
        results.mkdir()
        shutil.copy(self.made("reproduced", self._reproduced) / "results" / "reproduce.yaml",
                    results)
        for name in ("reports.jsonl.gz", "configs.jsonl.gz"):
            shutil.copy(packed / name, results / name)
        result = self.reproduce_again(results, "launcher=none")
        table = results / "table1.csv"
        rows = len(table.read_text().splitlines()) - 1 if table.is_file() else 0
        return result.describe() + (f"; HARMFUL: {rows} rows of the noise experiment in "
                                    "table1.csv" if rows > 0 else "; no row aggregated")

    def _noise_packed(self, path: Path) -> None:
        shutil.copytree(self.made("noise", self._noise) / "results", path / "results")
        result = self.tree.run("armeta-reproduce", "noise", "profile=tiny", "launcher=none",
                               "pack=true", f"results={path / 'results'}", cwd=path)
        if result.code != 0:
            raise RuntimeError(f"packing the noise sweep failed:\n{result.err[-3000:]}")

    def case_lock_hardlink(self) -> str:
        run_dir = self.stopped_tiny("lock_hardlink")
        outside = self.work / "lock_hardlink_outside.txt"
        outside.write_text("keep me\n")
        (run_dir / "run.lock").unlink(missing_ok=True)
        os.link(outside, run_dir / "run.lock")
        result = self.train(f"resume={run_dir}")
        kept = outside.read_text() == "keep me\n"
        return result.describe() + ("; the outside file untouched" if kept else
                                    "; HARMFUL: the outside file's text replaced")

    def special_in_results(self, name: str, file: str, *args: str) -> str:
        results = self.reproduced(name)
        path = results / "runs" / "sinusoid_uniform" / "maml" / "seed0" / file
        path.unlink()
        os.mkfifo(path)
        result = self.reproduce_again(results, "launcher=none", *args, timeout=90)
        return result.describe()

    def case_eval_json_fifo_pack(self) -> str:
        return self.special_in_results("eval_fifo", "eval.json", "pack=true")

    def case_config_fifo_pack(self) -> str:
        return self.special_in_results("config_fifo", "config.yaml", "pack=true")

    def case_config_fifo_eval(self) -> str:
        run_dir = self.finished_tiny("config_fifo_eval")
        (run_dir / "config.yaml").unlink()
        os.mkfifo(run_dir / "config.yaml")
        return self.tree.run("armeta-eval", f"learner={run_dir}",
                             f"out={self.work / 'config_fifo_eval' / 'out.json'}",
                             cwd=self.work, timeout=90).describe()

    def linked_log(self, name: str, relative: str) -> str:
        """``relative`` a link to a file outside the run holding a row a log could hold."""
        run_dir = self.stopped_tiny(name)
        outside = self.work / f"{name}_outside.txt"
        outside.write_text("1,0.5\n")
        log = run_dir / relative
        log.unlink(missing_ok=True)
        log.symlink_to(outside)
        result = self.train(f"resume={run_dir}")
        kept = outside.read_text() == "1,0.5\n"
        return result.describe() + ("; the outside file untouched" if kept else
                                    "; HARMFUL: the outside file written through the link")

    def case_log_symlink_resume(self) -> str:
        return self.linked_log("log_link", "logs/scalars/train/leader_loss.csv")

    def case_job_log_symlink_resume(self) -> str:
        return self.linked_log("job_log_link", "armeta-train.log")

    def case_frame_fifo_resume(self) -> str:
        run_dir = self.stopped_tiny("frame_fifo")
        frame = run_dir / "density" / "iter_000002.png"
        frame.unlink()
        os.mkfifo(frame)
        return self.train(f"resume={run_dir}", timeout=90).describe()

    @staticmethod
    def laughs(config: Path) -> None:
        """A config.yaml of nested aliases: ten times ten at nine levels, 10^9 strings."""
        lines = ['a0: &a0 ["lol","lol","lol","lol","lol","lol","lol","lol","lol","lol"]']
        lines += [f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * 10)}]" for i in range(1, 9)]
        config.write_text("\n".join(lines) + "\nseed: *a8\n")

    def case_yaml_aliases_resume(self) -> str:
        run_dir = self.stopped_tiny("laughs_resume")
        self.laughs(run_dir / "config.yaml")
        return self.train(f"resume={run_dir}", timeout=90, limit=ADDRESS_SPACE).describe()

    def case_yaml_aliases_eval(self) -> str:
        run_dir = self.finished_tiny("laughs_eval")
        self.laughs(run_dir / "config.yaml")
        return self.tree.run("armeta-eval", f"learner={run_dir}",
                             f"out={self.work / 'laughs_eval' / 'out.json'}", cwd=self.work,
                             timeout=90, limit=ADDRESS_SPACE).describe()

    def packed_file(self, name: str, write: Callable[[Path], None], **limits: int) -> str:
        results = self.reproduced(name)
        self.reproduce_again(results, "launcher=none", "pack=true")
        shutil.rmtree(results / "runs")
        write(results / "reports.jsonl.gz")
        result = self.reproduce_again(results, "launcher=none", timeout=300, **limits)
        return f"{result.describe()} after {result.seconds:.0f} s"

    @staticmethod
    def gzip_of(path: Path, chunk: bytes, times: int, end: bytes = b"") -> None:
        deflate = zlib.compressobj(6, zlib.DEFLATED, 16 + zlib.MAX_WBITS)
        with path.open("wb") as file:
            for _ in range(times):
                file.write(deflate.compress(chunk))
            file.write(deflate.compress(end) + deflate.flush())

    def case_packed_huge_line(self) -> str:
        return self.packed_file("huge_line", lambda path: self.gzip_of(
            path, b"a" * 2**20, 2**10, b"\n"), limit=2 * 2**30)

    def case_packed_many_lines(self) -> str:
        line = b'{"run":"runs/x/y/seed0","file":"eval.json","section":null,"report":{}}\n'
        return self.packed_file("many_lines", lambda path: self.gzip_of(
            path, line * 2**14, 1300 * 2**20 // (len(line) * 2**14)), limit=2 * 2**30)

    def case_packed_truncated(self) -> str:
        def cut(path: Path) -> None:
            data = path.read_bytes()
            path.write_bytes(data[: len(data) // 2])
        return self.packed_file("packed_cut", cut)

    def case_packed_bitflip(self) -> str:
        def flip(path: Path) -> None:
            data = bytearray(path.read_bytes())
            data[len(data) // 2] ^= 0x10
            path.write_bytes(bytes(data))
        return self.packed_file("packed_flip", flip)

    def case_spline_layers_huge(self) -> str:
        return self.bounded("spline_layers", "+risk.ar.flow_kwargs.layers=1000000")

    def case_spline_hidden_huge(self) -> str:
        return self.bounded("spline_hidden", "+risk.ar.flow_kwargs.hidden=1000000")

    def case_resume_long_component(self) -> str:
        return self.train(f"resume={self.work / ('x' * 300)}").describe()

    def case_max_steps_inf(self) -> str:
        run_dir = self.fresh("max_steps_inf") / "run"
        return self.train(*TINY, "benchmark=point_nav", "benchmark.collector.max_steps=inf",
                          f"hydra.run.dir={run_dir}").describe()

    def case_max_steps_huge(self) -> str:
        run_dir = self.fresh("max_steps_huge") / "run"
        return self.train(*TINY, "benchmark=point_nav",
                          "benchmark.collector.max_steps=1000000000000",
                          f"hydra.run.dir={run_dir}").describe()

    def case_figure_efbig(self) -> str:
        results = self.reproduced("efbig")
        (results / "table1.png").unlink(missing_ok=True)
        result = self.reproduce_again(results, "launcher=none", file_limit=32 * 2**10)
        return result.describe()

    def case_results_link_loop(self) -> str:
        home = self.fresh("results_loop")
        (home / "results").symlink_to(home / "results")
        return self.reproduce_again(home / "results", "launcher=none").describe()

    def case_hydra_n_jobs(self) -> str:
        home = self.fresh("n_jobs")
        return self.tree.run("armeta-reproduce", *REPRODUCE, "hydra.launcher.n_jobs=abc",
                             f"results={home / 'results'}", cwd=home).describe()

    def case_hydra_unknown_launcher(self) -> str:
        home = self.fresh("unknown_launcher")
        return self.train(*TINY, "-m", "hydra/launcher=nope",
                          f"hydra.sweep.dir={home / 'sweep'}", cwd=home).describe()

    def case_reproduce_partial(self) -> str:
        results = self.reproduced("partial")
        (results / "runs" / "sinusoid_uniform" / "maml" / "seed0" / "eval.json").unlink()
        result = self.reproduce_again(results, "launcher=none")
        named = "maml/seed0/eval.json" in result.err
        return result.describe() + ("; stderr names maml/seed0/eval.json and why" if named
                                    else "; stderr does not name the missing run")

    def case_fallback_warns(self) -> str:
        run_dir = self.stopped_tiny("fallback")
        state_pt = self.newest(run_dir) / "components" / "0000-leader" / "state.pt"
        data = bytearray(state_pt.read_bytes())
        data[len(data) // 2] ^= 0xFF
        state_pt.write_bytes(bytes(data))
        result = self.train(f"resume={run_dir}")
        warned = "broken" in result.err
        return result.describe() + ("; stderr warns of the checkpoint it set aside" if warned
                                    else "; stderr silent about the checkpoint set aside")

    def case_signal_final_eval(self) -> str:
        run_dir = self.fresh("final_eval") / "run"
        process = self.tree.start("armeta-train", *TINY, "eval.n_tasks=3000",
                                  f"hydra.run.dir={run_dir}", cwd=self.work)
        last = run_dir / "checkpoints" / "checkpoint-000000000006"
        wait_for(last.is_dir, process, 300, 0.05)
        time.sleep(1.0)
        evaluating = process.poll() is None and not (run_dir / "eval.json").exists()
        process.send_signal(signal.SIGTERM)
        result = Result.wait(process, 600)
        said = "final evaluation" in result.out + result.err
        return (f"{'signalled during the final evaluation' if evaluating else 'too late'}; "
                f"{result.describe()}; eval.json "
                f"{'written' if (run_dir / 'eval.json').is_file() else 'missing'}; "
                + ("the signal acknowledged" if said else "the signal not acknowledged"))

    def case_stale_staging(self) -> str:
        results = self.reproduced("stale_staging")
        gone = subprocess.Popen(["true"])
        gone.wait()
        staged = results / f".reports.jsonl.{gone.pid}.gz"
        staged.write_bytes(b"half a packed file")
        result = self.reproduce_again(results, "launcher=none")
        return result.describe() + ("; the stale staging file left" if staged.exists()
                                    else "; the stale staging file removed")

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


R = "armeta-train resume=RUN"
E = "armeta-eval learner=RUN"
P = "armeta-reproduce table1 profile=tiny benchmarks=sinusoid_uniform seeds=0"
TRUST_BEFORE = "f58bfba"
"""The revision the run-directory-as-data cases (issue 60) were first run against."""
TRUST_CASES = {
    "memmap_pickle_resume": ("the leader payload a TensorDict memory map with a pickled field "
                             "(the manifest resealed by the package's `seal`)", R),
    "memmap_pickle_eval": ("likewise", E),
    "memmap_pickle_frozen": ("likewise, in the run an attack loads",
                             "armeta-train method=ar_maml trainer.frozen_leader=RUN"),
    "memmap_pickle_adversary": ("likewise, in the adversary's run",
                                "armeta-eval learner=OTHER adversary=RUN"),
    "global_payload_resume": ("`state.pt` holding a pickle GLOBAL (`os.system`), resealed", R),
    "global_payload_eval": ("likewise", E),
    "payload_symlink": ("`state.pt` a symbolic link to a payload outside the run", R),
    "payload_hardlink": ("`state.pt` a hard link to a file outside the run", R),
    "checkpoint_dir_symlink": ("the newest `checkpoint-N` a link to a folder outside the run",
                               R),
    "checkpoint_no_identity": ("a seed-4 run's checkpoints, their identity removed (resealed), "
                               "in a seed-0 run", R),
    "checkpoint_no_identity_adopt": ("likewise, with the override",
                                     "armeta-train resume=RUN adopt=true"),
    "report_identity_removed": ("`dr_maml`'s `eval.json` in `maml/seed0`, its `seed` and "
                                "`config_sha256` deleted and `method` relabelled",
                                f"{P} launcher=none"),
    "pack_refused_report": ("likewise, packed", f"{P} launcher=none pack=true"),
    "other_experiment_run": ("the noise experiment's `maml/seed0` run directory in place of "
                             "table1's", f"{P} launcher=none"),
    "other_experiment_packed": ("the noise experiment's `reports.jsonl.gz` and "
                                "`configs.jsonl.gz` in a table1 results folder",
                                f"{P} launcher=none"),
    "lock_hardlink": ("`run.lock` a hard link to a file outside the run", R),
    "log_symlink_resume": ("a CSV log a link to a file outside the run", R),
    "job_log_symlink_resume": ("`armeta-train.log` a link to a file outside the run", R),
    "eval_json_fifo_pack": ("a run's `eval.json` a named pipe", f"{P} launcher=none pack=true"),
    "config_fifo_pack": ("a run's `config.yaml` a named pipe", f"{P} launcher=none pack=true"),
    "config_fifo_eval": ("`config.yaml` a named pipe", E),
    "frame_fifo_resume": ("a density frame a named pipe", R),
    "yaml_aliases_resume": ("a 1 kB `config.yaml` of nested YAML aliases (10^9 strings)", R),
    "yaml_aliases_eval": ("likewise", E),
    "packed_huge_line": ("`reports.jsonl.gz` of 1 MiB holding one 1 GiB line (2 GiB address "
                         "space)", f"{P} launcher=none"),
    "packed_many_lines": ("`reports.jsonl.gz` holding 1.3 GB of short lines (2 GiB address "
                          "space)", f"{P} launcher=none"),
    "packed_truncated": ("`reports.jsonl.gz` cut in half", f"{P} launcher=none"),
    "packed_bitflip": ("a bit of `reports.jsonl.gz` flipped", f"{P} launcher=none"),
    "spline_layers_huge": ("a million spline layers (cut after 120 s)",
                           "armeta-train +risk.ar.flow_kwargs.layers=1000000"),
    "spline_hidden_huge": ("a spline coupling a million units wide (cut after 120 s)",
                           "armeta-train +risk.ar.flow_kwargs.hidden=1000000"),
    "resume_long_component": ("a 300-byte path component", "armeta-train resume=…/xxx…"),
    "max_steps_inf": ("an episode length of infinity",
                      "armeta-train benchmark=point_nav benchmark.collector.max_steps=inf"),
    "max_steps_huge": ("an episode length no memory holds", "armeta-train benchmark=point_nav "
                       "benchmark.collector.max_steps=1000000000000"),
    "figure_efbig": ("files limited to 32 KiB (`ulimit -f 32`) as the figure is saved",
                     f"{P} launcher=none"),
    "results_link_loop": ("`results=` a link to itself", f"{P} results=LOOP"),
    "hydra_n_jobs": ("a launcher setting of the wrong type", f"{P} hydra.launcher.n_jobs=abc"),
    "hydra_unknown_launcher": ("a launcher Hydra does not have",
                               "armeta-train -m hydra/launcher=nope"),
    "reproduce_partial": ("a finished run's `eval.json` deleted", f"{P} launcher=none"),
    "fallback_warns": ("the newest checkpoint's leader payload garbled", R),
    "signal_final_eval": ("SIGTERM a second into the final evaluation (3,000 tasks)",
                          "armeta-train eval.n_tasks=3000"),
    "stale_staging": ("a `.reports.jsonl.<pid>.gz` a killed pack left",
                      f"{P} launcher=none"),
}
"""The cases of issue 60, each ``(case, command)``; RUN is the run directory the case
damaged."""
CODE_RAN = re.compile(r"CODE RAN")
HARMFUL = re.compile(r"HARMFUL")
HUNG = re.compile(r"timed out after|killed by SIGKILL")
"""A hang: cut by the campaign's time limit, or killed as it grew past its memory limit."""


class Pickled:
    """An object whose unpickling runs ``touch <marker>``: what a hostile payload would do."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self) -> tuple:
        return os.system, (f"touch {self.marker}",)


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


BEFORE = {"075b143": CASES, TRUST_BEFORE: TRUST_CASES}
"""Each group of cases and the revision its 'before' column runs."""


def counts(cases: dict[str, str], names: list[str]) -> str:
    """How many of ``names``' outcomes ran code, did harm, hung or ended in a traceback."""
    found = {label: sum(pattern.search(cases.get(name, "")) is not None for name in names)
             for label, pattern in (("code executed", CODE_RAN), ("harmful", HARMFUL),
                                    ("hangs", HUNG), ("tracebacks", CRASH))}
    return ", ".join(f"{n} {label}" for label, n in found.items())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rerun-before", action="store_true")
    parser.add_argument("--only", default="", help="comma-separated cases (default: all)")
    parser.add_argument("--skip-now", action="store_true",
                        help="run only the 'before' columns")
    args = parser.parse_args()
    names = [n for n in args.only.split(",") if n] or [*CASES, *TRUST_CASES]
    stored = json.loads(RESULTS.read_text()) if RESULTS.is_file() else {}
    before = stored.get("before", {})
    for revision, group in BEFORE.items():
        chosen = [name for name in names if name in group]
        known = before.setdefault(revision, {})
        todo = chosen if args.rerun_before else [n for n in chosen if n not in known]
        if todo:
            with tempfile.TemporaryDirectory(prefix="fault_campaign_tree_") as tree_dir:
                known.update(run_cases(Tree(extract(revision, Path(tree_dir)), revision), todo))
    stored["before"] = before
    if not args.skip_now:
        now = stored.get("now", {"cases": {}})
        label = current_label()
        now["cases"].update(run_cases(Tree(ROOT, label), names))
        now["revision"] = label
        stored["now"] = now
    RESULTS.write_text(json.dumps(stored, indent=1, sort_keys=True) + "\n")
    if "now" in stored:
        write_page(stored)


def write_page(stored: dict) -> None:
    """The ``fault_campaign`` section of docs/failures.md: a table per group of cases."""
    now = stored["now"]

    def cell(cases: dict[str, str], name: str) -> str:
        return TEMPORARY.sub("…/", cases.get(name, "–"))

    first, old = "075b143", stored["before"]["075b143"]
    rows = [(case, cell(old, name), cell(now["cases"], name)) for name, case in CASES.items()]
    table = markdown_table(("case", f"before ({first})", f"now ({now['revision']})"), rows)
    crashes = [sum(CRASH.search(cases.get(name, "")) is not None for name in CASES)
               for cases in (old, now["cases"])]
    trust = stored["before"][TRUST_BEFORE]
    trust_rows = [(case, f"`{command}`", cell(trust, name), cell(now["cases"], name))
                  for name, (case, command) in TRUST_CASES.items()]
    trust_table = markdown_table(("case", "command", f"before ({TRUST_BEFORE})",
                                  f"now ({now['revision']})"), trust_rows)
    write_section("fault_campaign", "The fault campaign", (
        "Each case run through the command-line tools as a user types it "
        "(`studies/fault_campaign.py`; raw outcomes in `studies/fault_campaign.json`; the "
        "columns may come from runs of some cases only, `--only`). Exit codes: 0 done, 1 a "
        "failed run or sweep, 2 bad input, 75 stopped by a preemption signal (resume it), 130 "
        "stopped by SIGINT. Cases ending in a traceback, a segfault or a death by a catchable "
        f"signal: {crashes[0]} of {len(CASES)} before, {crashes[1]} now.\n\n" + table
        + "\n\n### A run directory is data\n\nA run directory or results folder handed over "
        "by a hostile colleague, to be resumed, scored, attacked, aggregated or packed "
        "([the trust model](configuration.md#the-trust-model)); RUN is the run directory the "
        "case damaged, and a crafted payload's code would create a marker file. Harmful: "
        "wrong data trusted, a file outside the run written, or a refused report packed. "
        f"{len(TRUST_CASES)} cases; before ({TRUST_BEFORE}): "
        f"{counts(trust, list(TRUST_CASES))}; now: {counts(now['cases'], list(TRUST_CASES))}."
        "\n\n" + trust_table), PAGE,
        command="OMP_NUM_THREADS=1 python studies/fault_campaign.py")


if __name__ == "__main__":
    main()
