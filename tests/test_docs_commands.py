"""Every command block of README.md and docs/*.md runs, in order, as a newcomer would run it
(issue 20).

The rules (what runs, what is shortened, what is skipped and why):

* **Pages.** README.md, then every docs/*.md. One test per page; its blocks run in document
  order in one fresh temporary directory, with the repository's ``experiments/`` linked in as in
  a clone, so a block may use what an earlier block of the same page made (``runs/...``), and
  nothing is written into the repository.
* **Which blocks.** Fenced ```` ```bash ````, ```` ```sh ````, ```` ```shell ```` and
  ```` ```console ```` blocks run as shell scripts (``set -e``; ``&&`` chains become lines).
  A bare ```` ``` ```` block runs only when every line of it is a command (it starts with
  ``python``, ``pip``, ``pytest``, ``.``, ``source``, ``cd``, ``export`` or ``VAR=value``);
  other bare blocks are program output or diagrams. ```` ```python ```` blocks run in this
  process, in one namespace per page, like cells of a notebook session (the README's quick start
  defines the ``tokens`` and ``queries`` a later block uses). ```` ```text ````,
  ```` ```bibtex ```` and other languages never run.
* **Skipped, and said so** (the test prints every skipped command with its reason):

  - a block whose fence follows the line ``<!-- docs-test: skip (REASON) -->`` (blank lines
    between are allowed): the measurements a page reports beside their output, which take
    minutes to hours;
  - commands that run ``experiments/bench_*.py``, ``sweep_*.py``, ``ablate_*.py`` or
    ``check_*.py``: the benchmarks, sweeps, ablations and fingerprint checks behind the tables
    of docs/results.md (their names mark them as measurements, 1 min to 1 h each);
  - the pages of :data:`NOT_RUN` (docs/scaling.md: GPUs and several hosts);
  - set-up lines: ``python -m venv``, ``. .venv/bin/activate`` / ``source``, ``pip install``
    (the test runs in the environment the suite runs in), and ``pytest`` (this suite itself).

* **Shortened** (what the command does stays, its size shrinks; :data:`SHORTEN`):

  - ``python -m flowmaps_jax.train``: the smoke preset of the world the command trains on
    (``smoke``, ``homes-smoke``; with ``--data``, the files world's ``smoke``) replaces any
    preset (not with ``--resume``, which keeps the run's saved config; a preset the CLI does not
    know stays, and the command fails as it would for a user), ``--steps 4`` (``6`` with
    ``--resume``, so that it does continue), ``--no-progress``;
  - ``python -m flowmaps_jax.evaluate``: 2 environments, 4 samples, 4 KL draws, the accurate
    likelihood on its smallest grid (3 points; its 48-point RK4 solve, run without most of XLA's
    optimisations, was about a sixth of an evaluation of the shipped models);
  - ``python -m flowmaps_jax.search``: 2 environments, 8 samples;
  - commands that write into the repository or the installed package by default get an output
    directory in the temporary one: ``python -m flowmaps_jax.export`` (``--out exported``, never
    the packaged weights) and ``experiments/render_docs_figures.py`` (``--out figures``).

  Every other command runs as written.

* **In this process.** A shell block whose every command (as run) is ``python -m
  flowmaps_jax.<cli> ...`` or ``python <script>.py ...`` runs in the test's own process, one
  command after the other (:func:`support.run_python_in_process`: the module's ``main(argv)``,
  or the script as ``__main__``, in the temporary directory, its exit code and output checked
  as a subprocess's would be): JAX is imported once and the commands share compiled programs,
  which is most of this test's time. With XLA's ``jax_disable_most_optimizations``
  (:func:`support.fast_compile`; the programs are the same, compiled faster). Any other block
  (``VAR=value`` prefixes, ``python -c``, other programs) runs in ``bash`` as a script.

* **Each distinct command once.** A command the suite has already run (on this page or an
  earlier one) is not run again: its output (``--run-dir`` / ``--out``) is a copy of the first
  run's, kept aside when it ran (:class:`Ran`). Commands are compared after shortening, with their
  output option left out (a training into its default run directory is the same command as one
  into a named one; it has no copy to give a later command that names its output, which runs)
  and every input path that an earlier command made named by that command
  (``runs/a/checkpoints`` and ``runs/b/checkpoints`` are the same input when ``runs/a`` and
  ``runs/b`` were made by the same command). Only commands that name their output, and trainings
  (their default run directory is new each time and nothing names it), are compared; a
  ``--resume`` or ``--overwrite`` always runs, and so does a command whose output already exists
  (it must fail or act on it as written).

* **Known broken** blocks (:data:`KNOWN_BROKEN`: a page owner's fix is pending) run and must
  fail; once one passes, the test fails until it is taken off the list.

A failing block fails its page's test with the page and line, the command as run and the end of
its output. The smaller tests at the end check the rules themselves on made-up pages, including
that a failing command does fail.
"""

from __future__ import annotations

import dataclasses
import os
import pathlib
import re
import shlex
import shutil
import subprocess
import sys

import pytest
from support import fast_compile, run_python_in_process

REPO = pathlib.Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.usefixtures("fast_compiled_module")
PAGES = ["README.md", *sorted(str(p.relative_to(REPO)) for p in (REPO / "docs").glob("*.md"))]
NOT_RUN = {"docs/scaling.md": "needs GPUs or several hosts (CUDA jaxlib, --devices 4, two hosts)"}
KNOWN_BROKEN = {
    ("docs/results.md", "--steps 6000 --run-dir runs/mlp-cpu"):
        "the pre-issue-8 record trains into runs/flowmaps-cpu again, which a block above made "
        "(a run directory holds one run): it needs its own --run-dir or a skip mark",
}
SHELL_LANGS = {"bash", "sh", "shell", "console"}
COMMAND_WORDS = {"python", "pip", "pytest", ".", "source", "cd", "export"}
MEASUREMENT_SCRIPT = re.compile(r"(^|/)experiments/(bench|sweep|ablate|check)_\w*\.py$")
SKIP_MARK = re.compile(r"^<!--\s*docs-test:\s*skip\b\s*(.*?)\s*-->\s*$")
FENCE = re.compile(r"^```\s*([\w+-]*)\s*$")
TRAIN_STEPS, RESUME_STEPS = "4", "6"
# target (a -m module or an experiments/ script name) -> {option: value}; None: a flag
SHORTEN: dict[str, dict[str, str | None]] = {
    "flowmaps_jax.evaluate": {"--num-envs": "2", "--samples": "4", "--kl-draws": "4",
                              "--likelihood-steps": "3", "--no-progress": None},
    "flowmaps_jax.search": {"--num-envs": "2", "--samples": "8", "--no-progress": None},
}
DEFAULT_OUT = {"flowmaps_jax.export": "exported", "render_docs_figures.py": "figures"}


@dataclasses.dataclass
class Block:
    """One fenced block: page, line of its opening fence, language, code, skip reason."""

    page: str
    line: int
    lang: str
    code: str
    skip: str | None = None

    @property
    def where(self) -> str:
        return f"{self.page}:{self.line}"


def parse_blocks(page: str, text: str) -> list[Block]:
    """The fenced blocks of a Markdown page, in order."""
    lines, blocks, i = text.splitlines(), [], 0
    while i < len(lines):
        match = FENCE.match(lines[i])
        if not match:
            i += 1
            continue
        end = i + 1
        while end < len(lines) and not lines[end].startswith("```"):
            end += 1
        before = [line for line in lines[:i] if line.strip()]
        mark = SKIP_MARK.match(before[-1].strip()) if before else None
        skip = (mark.group(1).strip("() ") or "marked") if mark else None
        blocks.append(Block(page, i + 1, match.group(1).lower(), "\n".join(lines[i + 1:end]),
                            skip))
        i = end + 1
    return blocks


def _logical_lines(code: str) -> list[str]:
    """Lines with backslash continuations joined."""
    out, current = [], ""
    for line in code.splitlines():
        if line.rstrip().endswith("\\"):
            current += line.rstrip()[:-1] + " "
        else:
            out.append(current + line)
            current = ""
    if current:
        out.append(current)
    return out


def _split_commands(line: str) -> list[list[str]]:
    """A shell line's commands as argv lists (comments dropped; ``&&`` / ``;`` split)."""
    commands, current = [], []
    for token in shlex.split(line, comments=True):
        if token in ("&&", ";"):
            commands.append(current)
            current = []
        else:
            current.append(token)
    commands.append(current)
    return [c for c in commands if c]


def _program(argv: list[str]) -> tuple[list[str], list[str]]:
    """(leading VAR=value assignments, the command itself)."""
    n = 0
    while n < len(argv) and re.match(r"^[A-Za-z_][A-Za-z0-9_]*=", argv[n]):
        n += 1
    return argv[:n], argv[n:]


def is_command_block(block: Block) -> bool:
    """Whether a block is a shell block to run (see the module doc)."""
    if block.lang in SHELL_LANGS:
        return True
    if block.lang:
        return False
    lines = [line for line in _logical_lines(block.code) if line.strip()]
    try:
        commands = [c for line in lines for c in _split_commands(line)]
    except ValueError:  # unbalanced quotes: prose or output, not a command
        return False
    if not commands:
        return False
    return all(_program(c)[1][:1] and _program(c)[1][0] in COMMAND_WORDS for c in commands)


def _set_option(argv: list[str], option: str, value: str | None) -> list[str]:
    """argv with ``option`` set to ``value`` (replaced where present, else appended)."""
    out, i = [], 0
    while i < len(argv):
        if argv[i] == option:
            i += 1 if value is None else 2
            continue
        if argv[i].startswith(option + "="):
            i += 1
            continue
        out.append(argv[i])
        i += 1
    return [*out, option] if value is None else [*out, option, value]


def _target(argv: list[str]) -> str | None:
    """The module (``python -m X``) or script file name (``python path/X.py``) of a command."""
    if not argv or pathlib.PurePath(argv[0]).name not in ("python", "python3"):
        return None
    if len(argv) > 2 and argv[1] == "-m":
        return argv[2]
    if len(argv) > 1 and argv[1].endswith(".py"):
        return argv[1]
    return None


def _option_value(argv: list[str], option: str) -> str | None:
    """The value of ``option`` in ``argv`` (``--x V`` or ``--x=V``; the last one), or None."""
    value = None
    for i, arg in enumerate(argv):
        if arg == option and i + 1 < len(argv):
            value = argv[i + 1]
        elif arg.startswith(option + "="):
            value = arg.split("=", 1)[1]
    return value


def _smoke_preset(preset: str | None, data: bool) -> str | None:
    """The smoke preset (its first preset named ``*smoke``) of the world ``--preset PRESET``
    trains on, found in the world registry: among the worlds that read files with ``--data``,
    among the generated ones without (no ``--preset``: ``DEFAULT_PRESET``; with ``--data``, the
    files world's own default). None when the CLI does not know ``PRESET``."""
    from flowmaps_jax.training.config import DEFAULT_PRESET
    from flowmaps_jax.worlds import WORLDS

    given = preset or (None if data else DEFAULT_PRESET)
    for w in WORLDS.values():
        table = w.hook("presets") if w.reads_files == data else {}
        if table and (given is None or given in table):
            return next(name for name in table if name.endswith("smoke"))
    return None


def rewrite(argv: list[str]) -> tuple[list[str] | None, str | None]:
    """(the command to run, or None; why it was changed or dropped, or None)."""
    env, cmd = _program(argv)
    if not cmd:
        return argv, None
    target = _target(cmd)
    if cmd[0] in (".", "source") or target == "venv":
        return None, "set-up (a virtual environment; the test runs in one)"
    if cmd[0] == "pip" or target == "pip":
        return None, "set-up (installs; the test runs in the installed environment)"
    if cmd[0] == "pytest" or target == "pytest":
        return None, "the test suite itself"
    if target is None:
        return argv, None
    if MEASUREMENT_SCRIPT.search(target):
        return None, "a measurement script (benchmark, sweep, ablation or check)"
    name = pathlib.PurePath(target).name
    note = None
    if target == "flowmaps_jax.train":
        resume = "--resume" in cmd
        if not resume:
            smoke = _smoke_preset(_option_value(cmd, "--preset"), data="--data" in cmd)
            if smoke is None:  # a preset the CLI does not know: it fails as a user's would
                return [*env, *cmd], None
            cmd = _set_option(cmd, "--preset", smoke)
        cmd = _set_option(cmd, "--steps", RESUME_STEPS if resume else TRAIN_STEPS)
        cmd = _set_option(cmd, "--no-progress", None)
        note = "shortened training"
    for key in (target, name):
        for option, value in SHORTEN.get(key, {}).items():
            cmd = _set_option(cmd, option, value)
            note = "shortened"
        if key in DEFAULT_OUT and "--out" not in cmd:
            cmd = [*cmd, "--out", DEFAULT_OUT[key]]
            note = "output kept in the temporary directory"
    return [*env, *cmd], note


def shell_script(block: Block) -> tuple[str, list[str]]:
    """(the bash script to run for a command block, notes on every changed or dropped command)."""
    lines, notes = ["set -euo pipefail"], []
    for line in _logical_lines(block.code):
        for argv in _split_commands(line):
            run, note = rewrite(argv)
            if note:
                notes.append(f"{block.where}: {shlex.join(argv)}  ->  "
                             f"{shlex.join(run) if run else 'not run'} ({note})")
            if run:
                lines.append(shlex.join(run))
    return "\n".join(lines), notes


def in_process_commands(block: Block) -> list[list[str]] | None:
    """The commands of a shell block as run, if every one of them is ``python -m
    flowmaps_jax...`` or ``python <script>.py`` without ``VAR=value`` assignments: these run in
    the test's process (:func:`support.run_python_in_process`). None: the block runs in bash."""
    commands = []
    for line in _logical_lines(block.code):
        for argv in _split_commands(line):
            run, _ = rewrite(argv)
            if run is None:
                continue
            env, cmd = _program(run)
            target = _target(cmd)
            if env or target is None or not (target.startswith("flowmaps_jax.")
                                             or target.endswith(".py")):
                return None
            commands.append(cmd)
    return commands


OUTPUT_OPTIONS = ("--run-dir", "--out")


@dataclasses.dataclass
class Ran:
    """The distinct commands run so far (shared by the pages of one session): key -> (where it
    ran, a copy of its output or None); made: output path -> the key of the command that made
    it. ``cache``: where the copies are kept."""

    cache: pathlib.Path
    done: dict = dataclasses.field(default_factory=dict)
    made: dict = dataclasses.field(default_factory=dict)

    def key(self, cmd: list[str], workdir: pathlib.Path
            ) -> tuple[str | None, pathlib.Path | None]:
        """(the command's key, or None when it always runs; its output path, or None)."""
        out = next((workdir / cmd[i + 1] for i, token in enumerate(cmd[:-1])
                    if token in OUTPUT_OPTIONS), None)
        if "--resume" in cmd or "--overwrite" in cmd or (
                out is None and _target(cmd) != "flowmaps_jax.train"):
            return None, out
        words = []
        for i, token in enumerate(cmd):
            path = (workdir / token).resolve() if token and i and token[0] != "-" else None
            if token in OUTPUT_OPTIONS or (i and cmd[i - 1] in OUTPUT_OPTIONS):
                continue
            if path is not None and path.exists():
                origin = next((p for p in self.made if path == p or path.is_relative_to(p)), None)
                token = (f"<{self.made[origin]}>/{path.relative_to(origin)}" if origin
                         else str(path))
            words.append(token)
        return shlex.join(words), out

    def run(self, cmd: list[str], workdir: pathlib.Path, where: str
            ) -> tuple[int, str, str | None]:
        """Run ``cmd`` in ``workdir`` unless the same command ran before: (exit code, output,
        a note when it was not run again)."""
        key, out = self.key(cmd, workdir)
        if out is not None:  # what it writes is no longer what made it
            self.made = {p: k for p, k in self.made.items()
                         if not (p == out.resolve() or p.is_relative_to(out.resolve()))}
        if key in self.done and (out is None or (not out.exists() and self.done[key][1])):
            first, copy = self.done[key]
            if copy is not None and out is not None:
                shutil.copytree(copy, out, symlinks=True)
                self.made[out.resolve()] = key
            return 0, "", f"{where}: {shlex.join(cmd)}  ->  not run again (as at {first})"
        code, output = run_python_in_process(cmd[1:], workdir)
        if code == 0 and key is not None:
            copy = None
            if out is not None and out.exists():
                copy = self.cache / str(len(self.done))
                shutil.copytree(out, copy, symlinks=True)
                self.made[out.resolve()] = key
            self.done[key] = (where, copy)
        return code, output, None


def _known_broken(block: Block) -> str | None:
    return next((why for (page, text), why in KNOWN_BROKEN.items()
                 if page == block.page and text in block.code), None)


def run_page(page: str, text: str, workdir: pathlib.Path, namespace: dict | None = None,
             ran: Ran | None = None) -> list[str]:
    """Run a page's blocks in order in ``workdir``; returns the notes. AssertionError (with the
    block, the command and the end of its output) on the first block that fails. ``ran``: the
    commands already run (a fresh record when None)."""
    ran = Ran(workdir / ".ran") if ran is None else ran
    (workdir / "experiments").symlink_to(REPO / "experiments", target_is_directory=True)
    env = dict(os.environ, MPLBACKEND="Agg", PYTHONUNBUFFERED="1",
               PATH=os.pathsep.join([str(pathlib.Path(sys.executable).parent),
                                     os.environ.get("PATH", "")]))
    namespace = {} if namespace is None else namespace
    notes = []
    for block in parse_blocks(page, text):
        runnable = block.lang == "python" or is_command_block(block)
        if not runnable:
            continue
        if block.skip:
            notes.append(f"{block.where}: block not run ({block.skip})")
            continue
        broken = _known_broken(block)
        error = None
        if block.lang == "python":
            cwd = os.getcwd()
            os.chdir(workdir)
            try:
                exec(compile(block.code, block.where, "exec"), namespace)
            except Exception as err:  # reported below with the block
                error = f"{type(err).__name__}: {err}"
            finally:
                os.chdir(cwd)
        else:
            script, changed = shell_script(block)
            notes += changed
            commands = in_process_commands(block)
            if commands is not None:
                for command in commands:
                    code, output, note = ran.run(command, workdir, block.where)
                    notes += [note] if note else []
                    if code != 0:
                        error = f"exit code {code}\n$ {shlex.join(command)}\n{output[-4000:]}"
                        break
            else:
                proc = subprocess.run(["bash", "-c", script], cwd=workdir, env=env, text=True,
                                      stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                      timeout=900)
                if proc.returncode != 0:
                    error = f"exit code {proc.returncode}\n$ {script}\n{proc.stdout[-4000:]}"
        if broken:
            assert error is not None, (f"{block.where} runs now: take it off KNOWN_BROKEN "
                                       f"({broken})")
            notes.append(f"{block.where}: fails as known ({broken})")
        elif error is not None:
            raise AssertionError(f"{block.where} ({block.lang or 'shell'} block) failed: {error}")
    return notes


@pytest.fixture(scope="module")
def ran(tmp_path_factory) -> Ran:
    """The commands the pages of this module have run (each distinct one runs once)."""
    return Ran(tmp_path_factory.mktemp("ran"))


@pytest.mark.slow
@pytest.mark.parametrize("page", PAGES)
def test_every_command_block_runs_in_order(page, tmp_path, ran):
    if page in NOT_RUN:
        pytest.skip(f"{page}: {NOT_RUN[page]}")
    with fast_compile():
        notes = run_page(page, (REPO / page).read_text(), tmp_path, ran=ran)
    print("\n".join(notes))


def test_no_page_points_outside_the_repository():
    """Every relative link of README.md and docs/*.md names a file of the repository, and no page
    sends the reader to a path outside it (``../shared/...``)."""
    problems = []
    for page in PAGES:
        text = (REPO / page).read_text()
        for target in re.findall(r"\]\(([^)\s]+)\)", text):
            path = target.split("#")[0]
            if not path or re.match(r"^[a-z]+:", path):  # an anchor on the page, or a URL
                continue
            resolved = ((REPO / page).parent / path).resolve()
            if not resolved.is_relative_to(REPO) or not resolved.exists():
                problems.append(f"{page}: link to {target}")
        problems += [f"{page}: mentions {m}"  # a path, not an example inside one (/../..)
                     for m in re.findall(r"(?<![\w/=.])\.\./[\w./-]+", text)]
    assert not problems, "\n".join(problems)


# --------------------------------------------------------------------------- the rules themselves

PAGE = """# A page

```
python -m flowmaps_jax.train --run-dir runs/x   # about 25 min
```

```
preset    D layers    B   Q    params
cpu     128    4+4   64   8 2,309,296
```

<!-- docs-test: skip (a measurement) -->

```bash
python -c "raise SystemExit(1)"
```

```text
python -c "raise SystemExit(1)"
```
"""


def test_blocks_are_classified_and_marks_are_read():
    blocks = parse_blocks("page.md", PAGE)
    assert [(b.line, b.lang, b.skip) for b in blocks] == [
        (3, "", None), (7, "", None), (14, "bash", "a measurement"), (18, "text", None)]
    assert [is_command_block(b) for b in blocks] == [True, False, True, False]


def test_commands_are_shortened_or_dropped_by_the_rules():
    train = "python -m flowmaps_jax.train --preset paper --steps 30000 --run-dir runs/p"
    assert rewrite(shlex.split(train))[0] == shlex.split(
        "python -m flowmaps_jax.train --run-dir runs/p --preset smoke --steps 4 --no-progress")
    # the smoke preset of the command's world; a preset the CLI does not know stays as written
    for given, smoke in (("homes-rhythms", "homes-smoke"), ("habits", "smoke"),
                         ("homes --data d", "smoke")):
        assert rewrite(shlex.split(f"python -m flowmaps_jax.train --preset {given}"))[0][-5:] == [
            "--preset", smoke, "--steps", "4", "--no-progress"], given
    for unknown in ("--preset cpu-pointer", "--preset paper --data d"):
        command = shlex.split(f"python -m flowmaps_jax.train {unknown} --steps 7000")
        assert rewrite(command) == (command, None), unknown
    resume = rewrite(shlex.split("python -m flowmaps_jax.train --run-dir r --resume"))[0]
    assert "--preset" not in resume and resume[-3:] == ["--steps", "6", "--no-progress"]
    assert "--num-envs" in rewrite(shlex.split("python -m flowmaps_jax.evaluate --checkpoint x"))[0]
    export = rewrite(shlex.split("python -m flowmaps_jax.export --checkpoint c --name mlp"))[0]
    assert export[-2:] == ["--out", "exported"]
    for dropped in ("pip install -e .", ". .venv/bin/activate", "pytest",
                    "python -m venv .venv", "python experiments/bench_train.py --steps 10",
                    "python experiments/sweep_settings.py --steps 800"):
        assert rewrite(shlex.split(dropped))[0] is None, dropped
    chain = _split_commands("python -m venv .venv && . .venv/bin/activate && pip install -e .")
    assert [c[0] for c in chain] == ["python", ".", "pip"]


def test_cli_and_script_blocks_run_in_this_process():
    block = Block("page.md", 1, "bash", "pip install -e .\n"
                  "python -m flowmaps_jax.train --run-dir r && python experiments/quickstart.py")
    assert in_process_commands(block) == [
        ["python", "-m", "flowmaps_jax.train", "--run-dir", "r", "--preset", "smoke", "--steps",
         "4", "--no-progress"], ["python", "experiments/quickstart.py"]]
    for shell in ("python -c 'print(1)'", "XLA_FLAGS=--x python -m flowmaps_jax.train",
                  "python -m flowmaps_jax.train\nls runs", "python -m json.tool x.json"):
        assert in_process_commands(Block("page.md", 1, "bash", shell)) is None, shell


def test_a_command_in_this_process_fails_like_a_subprocess(tmp_path):
    (tmp_path / "fails.py").write_text("import sys\nprint('hello')\nsys.exit(3)\n")
    (tmp_path / "raises.py").write_text("raise RuntimeError('boom')\n")
    (tmp_path / "message.py").write_text("raise SystemExit('no way')\n")
    (tmp_path / "ok.py").write_text("import pathlib, sys\n"
                                    "pathlib.Path('out.txt').write_text(' '.join(sys.argv))\n")
    assert run_python_in_process(["fails.py"], tmp_path) == (3, "hello\n")
    code, output = run_python_in_process(["raises.py"], tmp_path)
    assert code == 1 and "RuntimeError: boom" in output
    assert run_python_in_process(["message.py"], tmp_path) == (1, "no way\n")
    assert run_python_in_process(["ok.py", "--a", "b"], tmp_path) == (0, "")
    assert (tmp_path / "out.txt").read_text() == "ok.py --a b"  # in its cwd, with its argv
    code, output = run_python_in_process(["-m", "flowmaps_jax.train", "--preset", "nope"],
                                         tmp_path)
    assert code == 2 and "nope" in output  # argparse's usage error


def test_a_failing_block_fails_its_page(tmp_path):
    for name in ("shell", "python", "skipped"):
        (tmp_path / name).mkdir()
    failing = "```bash\npython -c \"print('hello'); raise SystemExit(3)\"\n```\n"
    with pytest.raises(AssertionError, match=r"page.md:1 .*exit code 3(.|\n)*hello"):
        run_page("page.md", failing, tmp_path / "shell")
    with pytest.raises(AssertionError, match="NameError"):
        run_page("page.md", "```python\nprint(undefined_name)\n```\n", tmp_path / "python")
    skipped = "<!-- docs-test: skip (slow) -->\n```bash\nfalse\n```\n"
    assert run_page("page.md", skipped, tmp_path / "skipped") == ["page.md:2: block not run (slow)"]


def test_each_distinct_command_runs_once(tmp_path):
    """Pages share one record of what ran: a command seen before gets a copy of the first run's
    output, an input is named by the command that made it, and an existing output is run on."""
    script, log = tmp_path / "make.py", tmp_path / "log"
    script.write_text(
        "import pathlib, sys\n"
        f"open({str(log)!r}, 'a').write(' '.join(sys.argv[1:]) + '\\n')\n"
        "out = pathlib.Path(sys.argv[-1])\n"
        "value = (pathlib.Path(sys.argv[1]) / 'v').read_text() + '+' if len(sys.argv) > 3 "
        "else '0'\n"
        "out.mkdir(exist_ok=True)\n"
        "(out / 'v').write_text(value)\n")
    first = (f"```bash\npython {script} --out a\npython {script} --out b\n"
             f"python {script} a --out c\n```\n")
    second = (f"```bash\npython {script} --out x\npython {script} x --out y\n"
              f"python {script} --out x\n```\n")
    ran = Ran(tmp_path / "ran")
    for name in ("one", "two"):
        (tmp_path / name).mkdir()
    notes = run_page("one.md", first, tmp_path / "one", ran=ran)
    notes += run_page("two.md", second, tmp_path / "two", ran=ran)
    assert log.read_text().splitlines() == ["--out a", "a --out c", "--out x"]
    assert [(tmp_path / p / "v").read_text() for p in ("one/b", "one/c", "two/x", "two/y")] == [
        "0", "0+", "0", "0+"]
    assert sum("not run again (as at one.md:1)" in note for note in notes) == 3, notes

def test_a_training_into_its_default_run_directory_is_the_same_command(tmp_path, monkeypatch):
    """A training without ``--run-dir`` after the same into a named one is not run again; one
    into a named run directory after the same without runs (there is no copy to give it)."""
    calls = []

    def fake_run(args, cwd):
        calls.append(args)
        out = pathlib.Path(cwd) / args[args.index("--run-dir") + 1] if "--run-dir" in args else None
        if out is not None:
            out.mkdir(parents=True)
        return 0, ""

    monkeypatch.setitem(globals(), "run_python_in_process", fake_run)
    train = ["python", "-m", "flowmaps_jax.train", "--preset", "smoke"]
    named = Ran(tmp_path / "named")
    assert named.run([*train, "--run-dir", "runs/a"], tmp_path, "a.md:1")[2] is None
    assert "not run again (as at a.md:1)" in named.run(train, tmp_path, "a.md:2")[2]
    default = Ran(tmp_path / "default")
    assert default.run(train, tmp_path, "b.md:1")[2] is None
    assert default.run([*train, "--run-dir", "runs/b"], tmp_path, "b.md:2")[2] is None
    assert len(calls) == 3 and (tmp_path / "runs" / "b").is_dir()
