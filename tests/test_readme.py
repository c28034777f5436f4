"""The README is for users: short, every ncfix command in it a valid invocation, every link a page.

Fast by design: commands are parsed with the command line's own parser and their options checked
by the config code, not run (.ci/run runs the two set-up commands; other tests run the hook).
"""

from __future__ import annotations

import re
import shlex
import tomllib
from pathlib import Path

import pytest

from ncfix import cli
from ncfix.config import OPTION_NAMES, build_options, load_config

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
MAX_LINES = 250
BUILTIN_MACHINES = {p.stem for p in (REPO / "postprocessors").glob("*.toml")}
CORPUS_PREFIX = "../shared/corpus/"


def fenced(text: str, language: str) -> list[str]:
    return re.findall(rf"^```{language}\n(.*?)^```", text, re.S | re.M)


def ncfix_commands(text: str) -> list[str]:
    """Every command of a fenced bash block that runs ncfix, split out of `&&`, `;` and `|` chains."""
    commands = []
    for block in fenced(text, "bash"):
        for line in block.splitlines():
            line = line.split(" #", 1)[0].strip()
            for part in re.split(r"&&|\|\||;|\|", line):
                words = shlex.split(part)
                if words and words[0] in ("ncfix", ".venv/bin/ncfix"):
                    commands.append(part.strip())
    return commands


def arguments(command: str) -> list[str]:
    """The arguments ncfix itself gets: the shell's redirections removed."""
    words = shlex.split(command)[1:]
    out, skip = [], False
    for word in words:
        if skip:
            skip = False
            continue
        if word in (">", "<", ">>", "2>", "2>&1"):
            skip = word != "2>&1"
            continue
        if re.match(r"^\d?>>?|^<", word):  # >file, 2>file
            continue
        out.append(word)
    return out


def parser():
    build = getattr(cli, "build_parser", None) or cli._parser
    return build()


def links(text: str) -> list[str]:
    """Relative link targets of markdown links and images (no web addresses)."""
    return [t for t in re.findall(r"\]\(([^)\s]+)\)", text) if not re.match(r"^[a-z]+:", t)]


def anchor(heading: str) -> str:
    """GitHub's id for a heading: lower case, punctuation dropped, blanks to hyphens."""
    slug = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return slug.replace(" ", "-")


def anchors(page: Path) -> set[str]:
    text = re.sub(r"^```.*?^```", "", page.read_text(encoding="utf-8"), flags=re.S | re.M)
    return {anchor(h) for h in re.findall(r"^#+ (.+)$", text, re.M)}


README_TEXT = README.read_text(encoding="utf-8")
COMMANDS = ncfix_commands(README_TEXT)


def test_the_readme_is_short():
    lines = README_TEXT.count("\n")
    assert lines <= MAX_LINES, f"README.md has {lines} lines; keep it under {MAX_LINES + 1} (design goes to docs/)"


def test_the_readme_holds_ncfix_commands():
    assert len(COMMANDS) >= 4, COMMANDS
    assert any(c.startswith(".venv/bin/ncfix ") for c in COMMANDS), "the set-up command runs .venv/bin/ncfix"


@pytest.mark.parametrize("command", COMMANDS)
def test_every_ncfix_command_in_the_readme_is_a_valid_invocation(command):
    args_list = arguments(command)
    try:
        args = parser().parse_args(args_list)
    except SystemExit as exc:
        assert exc.code == 0, f"README command does not parse: {command}"
        return
    named = [args.input] if args.input != "-" else []
    named += list(args.part or []) + [p for p in (args.head, args.config) if p]
    for path in (p.split("@", 1)[0] for p in named):  # PATH@translate=…: the file is PATH
        if path.startswith(CORPUS_PREFIX):  # the public corpus beside the checkout, not in the repository
            if not (REPO / path).is_file():
                pytest.skip(f"corpus file {path} is absent")
            continue
        assert (REPO / path).is_file(), f"README command names {path}, which is not in the repository: {command}"
    if args.machine is not None and not args.machine.endswith(".toml"):
        assert args.machine in BUILTIN_MACHINES, f"unknown --machine {args.machine}: {command}"
    # The config file the command would read (-c, else ncfix.toml beside the input), then every
    # value checked by the code the command line uses.
    config_path = REPO / args.config if args.config else (REPO / args.input).parent / "ncfix.toml"
    config = load_config(config_path, explicit=bool(args.config)) if args.input != "-" else {}
    build_options(config, {name: getattr(args, name, None) for name in OPTION_NAMES}, where=str(config_path))


def test_the_readme_settings_example_is_a_valid_config(tmp_path):
    examples = [b for b in fenced(README_TEXT, "toml") if "[ncfix]" in b]
    assert examples, "the README shows a settings file"
    for example in examples:
        table = tomllib.loads(example)["ncfix"]
        assert set(table) <= set(OPTION_NAMES), set(table) - set(OPTION_NAMES)
        build_options(table, {})


@pytest.mark.parametrize("page", [README] + sorted((REPO / "docs").glob("*.md")) + [REPO / "BENCHMARKS.md"],
                         ids=lambda p: p.relative_to(REPO).as_posix())
def test_every_relative_link_points_at_a_file_and_heading(page):
    text = page.read_text(encoding="utf-8")
    for target in links(text):
        path, _, fragment = target.partition("#")
        dest = (page.parent / path).resolve() if path else page
        assert dest.exists(), f"{page.name} links to {target}, which does not exist"
        if fragment and dest.suffix == ".md":
            assert fragment in anchors(dest), f"{page.name} links to {target}: no such heading"


def test_the_readme_links_the_design_pages():
    targets = {t.partition("#")[0] for t in links(README_TEXT)}
    for page in ("collision", "correction", "deposit", "profiles", "performance", "contract"):
        assert f"docs/{page}.md" in targets, f"README.md does not link docs/{page}.md"


def test_docs_name_no_path_outside_the_clone_but_the_corpus():
    for page in [README, REPO / "BENCHMARKS.md", *sorted((REPO / "docs").glob("*.md"))]:
        text = page.read_text(encoding="utf-8")
        for match in re.finditer(r"\.\./shared/[\w./-]+", text):
            # The public corpus beside the checkout is the one place outside the clone docs may name
            # (its programs are public and the tests find them there).
            assert re.fullmatch(r"\.\./shared/corpus(/[\w.-]+)*", match.group(0).rstrip(".")), \
                f"{page.name} points users at {match.group(0)}"


def test_ci_runs_the_readme_test_command():
    """.ci/run runs the README's test command as a user would (its options included: -n, --dist, -m)."""
    runs = [part.strip() for block in fenced(README_TEXT, "bash") for line in block.splitlines()
            for part in line.split("&&") if part.strip().startswith(".venv/bin/pytest")]
    assert runs, "the README shows the test command"
    ci = (REPO / ".ci" / "run").read_text(encoding="utf-8")
    for command in runs:
        assert f'"$venv/bin/pytest" {command.removeprefix(".venv/bin/pytest ")}' in ci, f".ci/run does not run {command}"
