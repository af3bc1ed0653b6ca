"""The docs name what exists: every function docs/papers.md gives an equation's home is importable, every pointer
in the code to a document of the repository (docs/*.md, README.md) names one that is there."""
import importlib
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


#: the papers as docs/papers.md cites them (its first table gives each one's full citation)
PAPERS = ("Sensors 2022", "Muñoz 2018", "the JACO thesis", "Nelson 1995")


def equation_homes() -> list[tuple[str, ...]]:
    """The dotted names in the function column of docs/papers.md's equation table (``services.a.b.f``), and the
    bare names after one in the same cell, each with where it may live: beside the first (its class or module), or
    in the first's module."""
    names = []
    for line in (REPO / "docs" / "papers.md").read_text().splitlines():
        cells = line.split("|")
        if len(cells) < 5 or not re.match(rf"\s*({'|'.join(PAPERS)}|\(mfvs\))", cells[1]):
            continue
        dotted = re.findall(r"`(services\.[\w.]+)`", cells[3])
        assert dotted, line
        names += [(name,) for name in dotted]
        beside = dotted[0].rsplit(".", 1)[0]
        module = next(m for m in (beside, beside.rsplit(".", 1)[0]) if resolve(m) is not None and
                      type(resolve(m)).__name__ == "module")
        names += [(f"{beside}.{bare}", f"{module}.{bare}") for bare in re.findall(r"`(\w+)`", cells[3])]
    return names


def resolve(name: str):
    """The object a dotted name names (the longest importable module, then attributes), or None."""
    parts = name.split(".")
    for split in range(len(parts), 0, -1):
        try:
            target = importlib.import_module(".".join(parts[:split]))
        except ModuleNotFoundError:
            continue
        for attribute in parts[split:]:
            if not hasattr(target, attribute):
                return None
            target = getattr(target, attribute)
        return target
    return None


@pytest.mark.parametrize("names", equation_homes(), ids=lambda names: names[0])
def test_every_equation_has_the_home_docs_papers_gives_it(names):
    assert any(resolve(name) is not None for name in names), names


def test_the_equation_table_has_rows_of_every_paper():
    """(Rows the parser above does not recognise would go untested: each paper has rows.)"""
    table = (REPO / "docs" / "papers.md").read_text()
    for paper in PAPERS:
        assert f"\n| {paper} | " in table, paper
    assert len(equation_homes()) >= 30  # (30 when this was written)


def test_no_pointer_to_a_document_the_repository_does_not_have():
    missing = set()
    for path in [*REPO.glob("services/**/*.py"), *REPO.glob("protocol/*.py"), *REPO.glob("bench/*.py")]:
        for doc in re.findall(r"\b(docs/[\w-]+\.md|ARCHITECTURE\.md|README\.md)\b", path.read_text()):
            if not (REPO / doc).is_file():
                missing.add((str(path.relative_to(REPO)), doc))
    assert not missing, sorted(missing)
