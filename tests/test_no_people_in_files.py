"""No tracked file speaks of the sessions, engineers or agents that worked on the project: documents and comments say
what the code does and what was measured, with a date and a commit, not who measured it or in which sitting.

A few spellings are technical and stay: the viewer's module ``ovgaussian.view.session`` (one run of ``ovgaussian
view`` as a library call) and pytest's ``scope="session"``. They are removed from the text before the search, so any
other use of the word in the same line is still found."""

from __future__ import annotations

import re
import subprocess

from shared_data import REPO

#: Words that speak of the people or the sittings behind the work.
PEOPLE = re.compile(r"\bsessions?\b|\bengineers?\b|\bagents?\b", re.IGNORECASE)

#: Technical spellings of "session", removed before the search.
TECHNICAL = re.compile(
    r"ovgaussian[./]view[./]session(\.py)?"    # the viewer's module
    r"|``session``"                            # that module named in its package's docstring
    r"|\"session\"(?=[,\]])"                   # ... and in its package's __all__
    r"|scope=\"session\""                      # pytest's fixture scope
)

#: This file names the words it looks for.
EXEMPT = {"tests/test_no_people_in_files.py"}


def hits(text: str) -> list[tuple[int, str]]:
    """(line number, line) of every line of ``text`` that speaks of people or sessions."""
    return [(n, line.strip()) for n, line in enumerate(text.splitlines(), 1)
            if PEOPLE.search(TECHNICAL.sub("", line))]


def test_the_search_finds_the_words_and_leaves_the_technical_spellings():
    assert hits("Session 22: the profile from nothing") == [(1, "Session 22: the profile from nothing")]
    assert hits("measured in this session") and hits("eight engineers shared the cores") and hits("other agents")
    assert hits("sessions 20 and 21") and hits("x\nan engineer's fit") == [(2, "an engineer's fit")]
    assert hits("from ovgaussian.view.session import run_view") == []
    assert hits('@pytest.fixture(scope="session")') == []
    assert hits('__all__ = ["app", "config", "scene", "session", "state"]') == []
    assert hits("`ovgaussian/view/session.py`: one library call") == []
    assert hits("from ovgaussian.view.session import run_view  # as in session 12")
    assert hits("prompt engineering (Radford et al. 2021)") == []  # a technique, not a person


def test_no_tracked_file_speaks_of_sessions_or_engineers():
    names = subprocess.run(["git", "ls-files", "-z"], cwd=REPO, capture_output=True, check=True).stdout.split(b"\0")
    found, read, lines = [], 0, 0
    for name in filter(None, (n.decode() for n in names)):
        path = REPO / name
        if name in EXEMPT or not path.is_file():
            continue
        data = path.read_bytes()
        if b"\0" in data[:8192]:  # binary: images, weights
            continue
        text = data.decode("utf-8", errors="replace")
        read += 1
        lines += text.count("\n")
        found += [f"{name}:{n}: {line[:160]}" for n, line in hits(text)]
    # the whole tree was read, documents and code alike: not a pass over nothing
    assert read > 300 and lines > 50_000, (read, lines)
    assert found == [], "tracked files that speak of sessions or people:\n" + "\n".join(found)
