"""The docs are checked against the code: every `occdata ...` / `fastocc ...` command written in the code of
README.md and docs/*.md names a sub-command that exists and options its --help lists (current names; the old
spellings are hidden from --help and so refused here), every relative link and every repository path the
docs cite resolves, and no user page outgrows its word cap.

The commands are checked by walking the click command objects (no subprocess: the whole check takes well
under a second)."""

from __future__ import annotations

import functools
import re
import shlex
from dataclasses import dataclass
from pathlib import Path

import click
import pytest

from cli.fastocc_cli import main as fastocc_main
from cli.occdata_cli import main as occdata_main

REPO = Path(__file__).resolve().parents[1]
PROGRAMS: dict[str, click.Group] = {"occdata": occdata_main, "fastocc": fastocc_main}
# `python -m cli.occdata_cli ...` (and torchrun's `-m cli.fastocc_cli`) is the same program.
MODULES = {"cli.occdata_cli": "occdata", "cli.fastocc_cli": "fastocc"}
# Words that may stand before the program on a shell line: launchers, their options, prompts, env settings.
LAUNCHERS = {"$", ">", "time", "nohup", "exec", "env", "sudo", "torchrun", "python", "python3", "-m", "uv", "run",
             "timeout", "srun", "mpirun", "xargs", "command"}
SHELL_SPLIT = re.compile(r"\s(?:&&|\|\||\|)\s|;\s|;$|\$\(|`")
NUMBER = re.compile(r"^[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$")
ENV_SETTING = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*=")

# Word caps (47.9, 46.6). User pages say what to type and what to expect, and every page is one but
# these, which carry no cap: the changelog (a log) and the measurement pages, benchmarks-*.md and the
# ablation tables benchmarks/ablations.py writes (ablations.md).
MEASUREMENT_PAGES = {"CHANGELOG.md", "ablations.md"}
USER_PAGE_WORDS = 4000
PAGE_WORDS = {"labels.md": 3000}


@dataclass(frozen=True)
class Problem:
    """One thing wrong in a page: where (`page:line`) and what."""

    where: str
    what: str

    def __str__(self) -> str:
        return f"{self.where}: {self.what}"


# ---------------------------------------------------------------- the code in a page


def code_lines(text: str) -> list[tuple[int, str]]:
    """(line number, code) for every shell line of the fenced blocks (continuations joined; python, json,
    toml, yaml and text blocks left out) and every inline code span of the prose."""
    out: list[tuple[int, str]] = []
    lines = text.splitlines()
    i = 0
    while i < len(lines):
        fence = re.match(r"^\s*(```+|~~~+)\s*(\w*)", lines[i])
        if fence:
            marker, lang = fence.group(1), fence.group(2).lower()
            start = i
            i += 1
            block: list[tuple[int, str]] = []
            while i < len(lines) and not lines[i].strip().startswith(marker):
                block.append((i + 1, lines[i]))
                i += 1
            i += 1
            if lang not in ("python", "py", "json", "toml", "yaml", "text"):
                out.extend(_join_continuations(block, start + 2))
            continue
        for span in re.findall(r"(?<!`)`([^`\n]+)`(?!`)", lines[i]):
            out.append((i + 1, span))
        i += 1
    return out


def _join_continuations(block: list[tuple[int, str]], first: int) -> list[tuple[int, str]]:
    out: list[tuple[int, str]] = []
    pending, at = "", first
    for number, line in block:
        if not pending:
            at = number
        stripped = line.rstrip()
        if stripped.endswith("\\"):
            pending += stripped[:-1] + " "
            continue
        out.append((at, pending + line))
        pending = ""
    if pending:
        out.append((at, pending))
    return out


def commands_in(line: str) -> list[tuple[str, list[str]]]:
    """The (program, words after it) of each `occdata`/`fastocc` command on one shell line, its comment
    included (there a command is taken where a known sub-command follows the program's name)."""
    code, comment = _comment_split(line)
    found = []
    for segment in SHELL_SPLIT.split(code):
        words = _words(segment)
        for k, word in enumerate(words):
            program = _program(word, words[k - 1] if k else "")
            if program is None:
                continue
            if all(_launcher(w) for w in words[:k]):
                found.append((program, words[k + 1:]))
            break
    for segment in SHELL_SPLIT.split(comment):
        words = _words(segment)
        for k, word in enumerate(words[:-1]):
            program = _program(word, "")
            if program and words[k + 1] in PROGRAMS[program].commands:
                found.append((program, words[k + 1:]))
                break
    return found


def _comment_split(line: str) -> tuple[str, str]:
    """(code, comment) of a shell line: the comment starts at a `#` that begins a word."""
    m = re.search(r"(^|\s)#", line)
    return (line, "") if m is None else (line[:m.start()], line[m.end():])


def _words(segment: str) -> list[str]:
    try:
        return shlex.split(segment)
    except ValueError:  # an unbalanced quote in prose: plain words are good enough
        return segment.split()


def _program(word: str, before: str) -> str | None:
    name = word.rsplit("/", 1)[-1]
    if name in PROGRAMS:
        return name
    if before == "-m" and word in MODULES:
        return MODULES[word]
    return None


def _launcher(word: str) -> bool:
    return (word in LAUNCHERS or word.startswith("-") or ENV_SETTING.match(word) is not None
            or NUMBER.match(word) is not None or word.endswith(("/python", "/python3", "/torchrun")))


# ---------------------------------------------------------------- the checks


def _visible_options(command: click.Command, group: click.Group) -> set[str]:
    """The options `command --help` lists (the group's help names reach every sub-command)."""
    names = set()
    for param in command.params:
        if isinstance(param, click.Option) and not param.hidden:
            names.update(param.opts)
            names.update(param.secondary_opts)
    return names | set(group.context_settings.get("help_option_names", ["--help"]))


def _placeholder(word: str) -> bool:
    return word in ("...", "…") or word.startswith(("$", "<", "[", "{", "SUB", "COMMAND")) or word.isupper()


def check_command(program: str, words: list[str]) -> list[str]:
    """What is wrong with `program words...` (empty when nothing): an unknown sub-command or options that
    its --help does not list."""
    group = PROGRAMS[program]
    group_options = _visible_options(group, group)
    problems: list[str] = []
    k = 0
    while k < len(words) and words[k].startswith("-"):
        if words[k].split("=", 1)[0] not in group_options:
            problems.append(f"`{program}` has no option {words[k]}")
        k += 1
    if k == len(words) or _placeholder(words[k]):
        return problems
    name = words[k].strip(".,:;)")
    command = group.commands.get(name)
    if command is None:
        return [*problems, f"`{program}` has no sub-command {name!r}"]
    allowed = _visible_options(command, group)
    for word in words[k + 1:]:
        option = word.strip("[](),;").split("=", 1)[0]
        if not option.startswith("-") or option in ("-", "--") or NUMBER.match(option) or "…" in option:
            continue
        option = option.rstrip(".")  # `--flag...` / `--flag.` in prose
        if option not in allowed:
            problems.append(f"`{program} {name}` has no option {option}")
    return problems


MD_LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
# A repository path written bare (`docs/store.md`, scripts/demo.sh): from the repository root. One inside
# another project (`OpenOccupancy/docs/x.md`) or a commit (`git show abc123:docs/x.json`) is not ours.
BARE_PATH = re.compile(r"(?<![\w./:-])((?:docs|scripts|benchmarks|tests|occdata|fastocc|cli)/[\w./-]*[\w/])")
LICENSE_NAMES = ("LICENSE", "README.md", "pyproject.toml")


def slug(heading: str) -> str:
    """GitHub's anchor for a markdown heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"[`*]|\[([^\]]*)\]\([^)]*\)", r"\1", heading.strip()).lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


@functools.cache
def anchors(page: Path) -> set[str]:
    """The section anchors GitHub gives a page's headings (a repeated heading gets -1, -2, ...)."""
    seen: dict[str, int] = {}
    out = set()
    in_fence = False
    for line in page.read_text(encoding="utf-8").splitlines():
        if line.lstrip().startswith(("```", "~~~")):
            in_fence = not in_fence
        m = None if in_fence else re.match(r"^#{1,6}\s+(.*?)\s*#*\s*$", line)
        if m:
            base = slug(m.group(1))
            n = seen.get(base, 0)
            seen[base] = n + 1
            out.add(base if n == 0 else f"{base}-{n}")
    return out


def check_link(page: Path, target: str, repo: Path) -> str | None:
    """What is wrong with a link from `page` to `target` (None when it resolves)."""
    if re.match(r"^[a-z][a-z0-9+.-]*:", target) or target.startswith("//"):
        return None  # a URL, mailto: ...
    path, _, anchor = target.partition("#")
    dest = (page.parent / path).resolve() if path else page
    if not dest.exists():
        return f"link to {target}: no such file"
    if _outside(dest, repo):
        return f"link to {target}: outside the repository"
    if anchor and dest.suffix == ".md" and anchor not in anchors(dest):
        return f"link to {target}: {dest.name} has no section #{anchor}"
    return None


def _outside(path: Path, repo: Path) -> bool:
    try:
        path.relative_to(repo.resolve())
    except ValueError:
        return True
    return False


def check_bare_path(page: Path, path: str, repo: Path) -> str | None:
    """A repository path named in a page (from the root; from the page's folder also accepted)."""
    if any(c in path for c in "*<>{}$") or "..." in path:
        return None
    if (repo / path).exists() or (page.parent / path).exists():
        return None
    if "." not in path.rsplit("/", 1)[-1] and not path.endswith("/"):
        return None  # `occdata/labels` in prose is a module, checked when it has a suffix or a slash
    return f"names {path}: no such file in the repository"


def check_text(page: Path, text: str, repo: Path = REPO) -> list[Problem]:
    """Every problem in one page's text (`page` locates its relative links). The changelog records old
    spellings and removed files on purpose: only its links are checked."""
    rel = page.name if page.parent.name != "docs" else f"docs/{page.name}"
    history = page.name == "CHANGELOG.md"
    problems: list[Problem] = []
    for number, line in [] if history else code_lines(text):
        for program, words in commands_in(line):
            problems += [Problem(f"{rel}:{number}", p) for p in check_command(program, words)]
    for number, line in enumerate(text.splitlines(), 1):
        for target in MD_LINK.findall(line):
            what = check_link(page, target, repo)
            if what:
                problems.append(Problem(f"{rel}:{number}", what))
        if history:
            continue
        for path in BARE_PATH.findall(MD_LINK.sub("", line)):
            what = check_bare_path(page, path, repo)
            if what:
                problems.append(Problem(f"{rel}:{number}", what))
        if "../shared" in line:
            problems.append(Problem(f"{rel}:{number}", "cites ../shared (outside the repository)"))
        if re.search(r"DESIGN(\.md)? ?§", line):
            problems.append(Problem(f"{rel}:{number}", "cites DESIGN §, a file the repository lacks"))
    return problems


def pages(repo: Path = REPO) -> list[Path]:
    return [repo / "README.md", *sorted((repo / "docs").glob("*.md"))]


def words_in(text: str) -> int:
    return len(text.split())


# ---------------------------------------------------------------- the tests


@pytest.mark.parametrize("page", pages(), ids=lambda p: str(p.relative_to(REPO)))
def test_page_commands_and_links(page: Path) -> None:
    problems = check_text(page, page.read_text(encoding="utf-8"))
    assert not problems, "\n".join(map(str, problems))


@pytest.mark.parametrize("page", [p for p in pages() if p.parent.name == "docs" and p.name not in MEASUREMENT_PAGES
                                  and not p.name.startswith("benchmarks")] + [REPO / "README.md"],
                         ids=lambda p: str(p.relative_to(REPO)))
def test_user_page_word_cap(page: Path) -> None:
    cap = PAGE_WORDS.get(page.name, USER_PAGE_WORDS) if page.parent.name == "docs" else USER_PAGE_WORDS
    n = words_in(page.read_text(encoding="utf-8"))
    assert n <= cap, f"{page.name} has {n} words (a user page has at most {cap}; measurements go to benchmarks-*.md)"


def test_readme_keeps_its_two_commands_and_results_table() -> None:
    text = (REPO / "README.md").read_text(encoding="utf-8")
    assert "bash scripts/demo.sh" in text and "bash scripts/test.sh" in text
    assert "\n## Results\n" in text


def test_the_checker_finds_a_wrong_option_a_wrong_command_and_a_broken_link(tmp_path: Path) -> None:
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "there.md").write_text("# A section\n\ntext\n", encoding="utf-8")
    page = tmp_path / "docs" / "page.md"
    text = (
        "Build it:\n\n"
        "```bash\n"
        "occdata build --root $ROOT \\\n"
        "    --out store.zarr --grid occ3d   # --grid is build's old spelling\n"
        "OMP_NUM_THREADS=1 python -m cli.fastocc_cli train --store s.zarr --epochs 2 --no-such-flag\n"
        "```\n\n"
        "Then `occdata labels --lidar-sweeps` and `fastocc frobnicate --store x` and `occdata labels --all-sweeps`.\n"
        "See [there](there.md), [the section](there.md#a-section), [gone](missing.md), [bad](there.md#nope) "
        "and `docs/nowhere.md`.\n"
    )
    found = [str(p) for p in check_text(page, text, repo=tmp_path)]
    assert found == [
        "docs/page.md:4: `occdata build` has no option --grid",
        "docs/page.md:6: `fastocc train` has no option --no-such-flag",
        "docs/page.md:9: `occdata labels` has no option --lidar-sweeps",
        "docs/page.md:9: `fastocc` has no sub-command 'frobnicate'",
        "docs/page.md:10: link to missing.md: no such file",
        "docs/page.md:10: link to there.md#nope: there.md has no section #nope",
        "docs/page.md:10: names docs/nowhere.md: no such file in the repository",
    ]


def test_the_checker_passes_what_is_right() -> None:
    text = (
        "```bash\n"
        "# a comment: occdata build --gts-grid occ3d\n"
        "occdata synth --out demo/world --scenes 1 && occdata build --root demo/world --out demo/store.zarr \\\n"
        "   --range -40 -40 -1 40 40 5.4 ...\n"
        "torchrun --nproc_per_node 2 -m cli.fastocc_cli train --store demo/store.zarr --epochs 1\n"
        "occdata --help; fastocc train -h; occdata dump -i 3 --store s.zarr\n"
        "```\n"
        "```python\n"
        "import occdata\nfrom occdata.labels import scene  # occdata labels --bogus is python here\n"
        "```\n"
        "Inline `occdata labels --all-sweeps --no-boxes` and `occdata/labels/carve.py` and `occdata ...`.\n"
    )
    assert check_text(REPO / "docs" / "x.md", text) == []


def test_old_spellings_are_refused_although_still_accepted() -> None:
    """The renamed options still parse (hidden from --help), but the docs must use the new names."""
    assert check_command("occdata", ["labels", "--lidar-sweeps"]) == ["`occdata labels` has no option --lidar-sweeps"]
    assert check_command("occdata", ["build", "--gts-grid", "occ3d"]) == []


def test_slug_matches_github() -> None:
    assert slug("3. The store: layout & chunks") == "3-the-store-layout--chunks"
    assert slug("Frames and `T_a_from_b` names") == "frames-and-t_a_from_b-names"
