"""The README is a map: every file, command, flag and parameter it names exists.

Read from the README's inline code, its shell blocks (indented four spaces), its links and its
TOML excerpt: paths are checked against the repository, `zenpilot` subcommands and flags against
`deploy.cli.build_parser()`, `zenpilot-<service>` commands against pyproject's scripts and their
own parsers, `service.key` parameters against each service's declared defaults and the stack file,
the TOML excerpt against `deploy/stacks/default.toml`. The Python block (the MAVSDK script) is
tests/integration/test_mavsdk.py's to check.
"""

from __future__ import annotations

import argparse
import contextlib
import fnmatch
import importlib
import io
import re
import shlex
import tomllib
from functools import cache
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
README = ROOT / "README.md"
MAX_BYTES = 8000            # issue 23: the README <= 8 kB (the strict reading)
FIRST_SCREEN_LINES = 40     # ... with the folder map in its first screen

# not files of the repository: what the install or a flight makes, and Zenoh key expressions
NOT_REPO_PREFIXES = ("runs/", ".venv/", "~/", "zp/")
PATH_RE = re.compile(r"^[A-Za-z0-9_.\-/<>*]+$")
FILE_EXT_RE = re.compile(r"\.(py|toml|md|json|png|txt|html|mcap|log|yaml|cfg)$")
FLAG_RE = re.compile(r"(?<![\w-])(--?[A-Za-z][\w-]*)")


# ---------------------------------------------------------------- what the code declares
@cache
def _services() -> dict[str, str]:
    from services.stack import SERVICE_MODULES
    return dict(SERVICE_MODULES)


@cache
def _params(service: str) -> frozenset[str]:
    """The service's declared defaults and the keys the stack file gives it."""
    module = importlib.import_module(_services()[service])
    defaults = module.param_defaults() if hasattr(module, "param_defaults") else getattr(module, "PARAMS")
    stack = tomllib.loads((ROOT / "deploy/stacks/default.toml").read_text())
    given = stack.get("services", {}).get(service, {}).get("params", {})
    return frozenset(defaults) | frozenset(given)


@cache
def _scripts() -> dict[str, str]:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]


@cache
def _script_flags(script: str) -> frozenset[str]:
    """The option strings of a `zenpilot-*` command, from its own --help."""
    module, func = _scripts()[script].split(":")
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.suppress(SystemExit):
        getattr(importlib.import_module(module), func)(["--help"])
    return frozenset(FLAG_RE.findall(out.getvalue()))


@cache
def _cli() -> argparse.ArgumentParser:
    from deploy.cli import build_parser
    return build_parser()


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


@cache
def _all_flags() -> frozenset[str]:
    flags: set[str] = set()
    todo = [_cli()]
    while todo:
        p = todo.pop()
        flags |= set(p._option_string_actions)
        todo += _subparsers(p).values()
    for script in _scripts():
        flags |= _script_flags(script)
    return frozenset(flags)


@cache
def _written_names() -> str:
    """Source of the code that writes a flight's files (file names a run makes, e.g. metrics.json)."""
    return "".join(p.read_text() for d in ("deploy", "services", "schemas") for p in sorted((ROOT / d).glob("*.py")))


# ---------------------------------------------------------------- reading the README
def _split(text: str) -> tuple[list[str], list[str], list[str]]:
    """(inline code spans and link targets, shell command lines, TOML blocks)."""
    spans, shell, toml = [], [], []
    prose = []
    fence = None
    block: list[str] = []
    for line in text.splitlines():
        if fence is not None:
            if line.startswith("```"):
                if fence == "toml":
                    toml.append("\n".join(block))
                fence, block = None, []
            else:
                block.append(line)
        elif line.startswith("```"):
            fence = line[3:].strip()
        elif line.startswith("    ") and line.strip():
            shell.append(line.strip())
        else:
            prose.append(line)
    body = "\n".join(prose)
    spans += re.findall(r"`([^`]+)`", body)
    spans += [t for t in re.findall(r"\]\(([^)\s]+)\)", body) if "://" not in t and not t.startswith("#")]
    return spans, shell, toml


def _check_path(token: str, problems: list[str]) -> None:
    token = token.split("#")[0]
    if not token or token.startswith(NOT_REPO_PREFIXES) or not PATH_RE.match(token):
        return
    if "/" not in token:
        if FILE_EXT_RE.search(token) and not (ROOT / token).exists() and f'"{token}"' not in _written_names():
            problems.append(f"file {token!r}: not in the repository, nor a file the code writes")
        return
    if "<" in token or "*" in token:
        pattern = re.sub(r"<[^>]*>", "*", token).rstrip("/")
        if not list(ROOT.glob(pattern)):
            problems.append(f"path {token!r}: nothing in the repository matches")
    elif not (ROOT / token).exists():
        problems.append(f"path {token!r}: not in the repository")


def _resolves(dotted: str) -> bool:
    parts = dotted.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        try:
            for name in parts[i:]:
                obj = getattr(obj, name)
        except AttributeError:
            return False
        return True
    return False


def _check_param(service: str, key: str, where: str, problems: list[str]) -> None:
    if service not in _services():
        problems.append(f"{where}: {service!r} is not a service ({', '.join(_services())})")
    elif not any(fnmatch.fnmatchcase(k, key) for k in _params(service)):
        problems.append(f"{where}: {service} has no parameter {key!r}")


def _check_zenpilot(tokens: list[str], where: str, problems: list[str]) -> None:
    from services.stack import available_missions
    parser, chain = _cli(), "zenpilot"
    args = iter(tokens[1:])
    for tok in args:
        subs = _subparsers(parser)
        if tok.startswith("-") and len(tok) > 1:
            flag, _, value = tok.partition("=")
            action = parser._option_string_actions.get(flag)
            if action is None:
                problems.append(f"{where}: `{chain}` has no flag {flag}")
                continue
            if action.nargs == 0 or (action.nargs == "?" and not value):
                continue
            value = value or next(args, "")
            if flag == "--set":
                service, _, rest = value.partition(".")
                _check_param(service, rest.split("=")[0], f"{where}: --set {value}", problems)
            elif flag == "--mission" and value not in (*available_missions(), "none") \
                    and not (ROOT / value).is_file():
                problems.append(f"{where}: no mission {value!r} ({', '.join(available_missions())})")
        elif subs:
            if tok not in subs:
                problems.append(f"{where}: `{chain}` has no subcommand {tok!r} ({', '.join(subs)})")
                return
            parser, chain = subs[tok], f"{chain} {tok}"
    if parser is not _cli() and _subparsers(parser):   # `zenpilot log` alone; `zenpilot` alone names the program
        problems.append(f"{where}: `{chain}` needs a subcommand ({', '.join(_subparsers(parser))})")


def _check_script(tokens: list[str], where: str, problems: list[str]) -> None:
    name = tokens[0]
    matches = fnmatch.filter(_scripts(), re.sub(r"<[^>]*>", "*", name))
    if not matches:
        problems.append(f"{where}: no command {name} (pyproject's scripts: {', '.join(_scripts())})")
        return
    service = name.removeprefix("zenpilot-")
    args = iter(tokens[1:])
    for tok in args:
        if not tok.startswith("-") or len(tok) == 1:
            continue
        flag, _, value = tok.partition("=")
        missing = [m for m in matches if flag not in _script_flags(m)]
        if missing:
            problems.append(f"{where}: {', '.join(missing)} has no flag {flag}")
        elif flag == "--param" and service in _services():
            _check_param(service, (value or next(args, "")).split("=")[0], f"{where}: --param", problems)


def _check_command(line: str, where: str, problems: list[str]) -> None:
    for segment in re.split(r"&&|\|\||[;|&]", line):
        try:
            tokens = shlex.split(segment, comments=True)
        except ValueError as exc:
            problems.append(f"{where}: cannot read {segment!r} ({exc})")
            continue
        if not tokens:
            continue
        exe = tokens[0].rsplit("/", 1)[-1]
        if tokens[0].startswith(".venv/bin/"):
            tokens[0] = exe
        if exe == "zenpilot":
            _check_zenpilot(tokens, where, problems)
        elif exe.startswith("zenpilot-"):
            _check_script([exe, *tokens[1:]], where, problems)
        for tok in tokens[1:]:
            if not tok.startswith("-"):
                _check_path(tok, problems)


def _check_toml(block: str, problems: list[str]) -> None:
    """A TOML excerpt shows the stack file as it is: every key, the file's value."""
    stack = tomllib.loads((ROOT / "deploy/stacks/default.toml").read_text())

    def walk(shown, real, where):
        for key, value in shown.items():
            if not isinstance(real, dict) or key not in real:
                problems.append(f"TOML excerpt: {where}{key} is not in deploy/stacks/default.toml")
            elif isinstance(value, dict):
                walk(value, real[key], f"{where}{key}.")
            elif value != real[key]:
                problems.append(f"TOML excerpt: {where}{key} = {value!r}, the stack file has {real[key]!r}")
    try:
        walk(tomllib.loads(block), stack, "")
    except tomllib.TOMLDecodeError as exc:
        problems.append(f"TOML excerpt: not valid TOML ({exc})")


def readme_problems(text: str) -> list[str]:
    """Everything the text names that does not exist, one line each."""
    problems: list[str] = []
    spans, shell, toml = _split(text)
    for span in spans:
        where = f"`{span}`"
        first = span.split()[0] if span.split() else ""
        if first.rsplit("/", 1)[-1] == "zenpilot" or first.startswith("zenpilot-"):
            _check_command(span, where, problems)
            continue
        for word in span.split():
            if word.startswith("-") and len(word) > 1:
                flag = word.partition("=")[0]
                if flag not in _all_flags():
                    problems.append(f"{where}: no command has the flag {flag}")
            else:
                _check_path(word, problems)
        dotted = re.fullmatch(r"([a-z_]+)((?:\.[A-Za-z_][\w*]*)+)(=.*)?", span)
        if dotted and not FILE_EXT_RE.search(span.split("=")[0]):
            if (ROOT / dotted[1] / "__init__.py").is_file():   # flight.quat, flight.control.laws.stopping_rate
                if not _resolves(dotted[1] + dotted[2]):
                    problems.append(f"{where}: no such module or attribute in the repository")
            else:
                _check_param(dotted[1], dotted[2][1:], where, problems)
    for line in shell:
        _check_command(line, f"command `{line}`", problems)
    for block in toml:
        _check_toml(block, problems)
    return problems


# ---------------------------------------------------------------- tests
def test_readme_names_only_what_exists():
    assert readme_problems(README.read_text()) == []


def test_readme_is_a_map():
    text = README.read_text()
    assert len(text.encode()) <= MAX_BYTES, f"README.md is {len(text.encode())} bytes (at most {MAX_BYTES})"
    first_screen = "\n".join(text.splitlines()[:FIRST_SCREEN_LINES])
    assert "| `flight/` |" in first_screen and "| `services/` |" in first_screen, "the folder map, in the first screen"


def test_the_check_finds_what_does_not_exist():
    """Each kind of name the README could get wrong is reported (the stale one of issue 23 too)."""
    bad = """
Set `flip.plan_rate_hz` or `attitude.no_such_gain` (`flight.no_such_module`, `flight.quat.no_such`); the code is in `flight/no_such.py`, see
[the notes](docs/no-such.md) and `nosuch/<name>.py`; the file `nothing.json`; `--no-such-flag`.

    zenpilot fly --lockstep --mission no-such-mission --set position.kk=[1,1,1]
    zenpilot flyy --lockstep
    zenpilot log inspect runs/h3
    zenpilot log
    zenpilot up --detatch
    zenpilot-attitude --param nope=1 --bogus
    zenpilot-nosuch -e tcp/127.0.0.1:7447

```toml
[services.attitude]
rate_hz = 99.0
no_such_key = 1
```
"""
    found = "\n".join(readme_problems(bad))
    for expected in ("'flip' is not a service", "`flight.no_such_module`: no such module", "`flight.quat.no_such`: no such module", "attitude has no parameter 'no_such_gain'",
                     "path 'flight/no_such.py'", "path 'docs/no-such.md'", "path 'nosuch/<name>.py'",
                     "file 'nothing.json'", "no command has the flag --no-such-flag",
                     "no mission 'no-such-mission'", "position has no parameter 'kk'",
                     "has no subcommand 'flyy'", "`zenpilot log` has no subcommand 'inspect'", "`zenpilot log` needs a subcommand",
                     "`zenpilot up` has no flag --detatch", "attitude has no parameter 'nope'",
                     "zenpilot-attitude has no flag --bogus", "no command zenpilot-nosuch",
                     "services.attitude.rate_hz = 99.0",
                     "services.attitude.no_such_key is not in deploy/stacks/default.toml"):
        assert expected in found, f"not reported: {expected}\n{found}"
    assert readme_problems("""
`attitude.k`, `flight.quat`, `flight.control.laws.stopping_rate`, `services/attitude.py`, `--lockstep`, [messages](docs/messages.md), `metrics.json`

    zenpilot fly --lockstep --mission flip --set planner.mpc_rate_hz=200
    zenpilot-attitude -e tcp/127.0.0.1:7447 --param k=[12,12,12]
""") == []
