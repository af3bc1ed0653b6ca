"""Tests mirror the modules they test: ``tests/<package path>/test_<module>[_<aspect>].py`` tests
``<package path>/<module>.py`` (or a script, ``.sh``; ``test_main`` tests ``__main__.py``); at the top of tests/ only the tests that cross
the whole stack."""
from tests.helpers import REPO

CROSS_CUTTING = {"test_imports.py", "test_latency.py", "test_fuzz_services.py", "test_shipped_configs.py",
                 "test_layout.py"}


def module_of(test_name: str) -> str:
    stem = test_name.removeprefix("test_").removesuffix(".py")
    return "__main__" if stem == "main" else stem


def test_every_test_file_sits_where_its_module_does():
    tests = REPO / "tests"
    orphans = []
    for path in sorted(tests.rglob("test_*.py")):
        relative = path.relative_to(tests)
        if len(relative.parts) == 1:
            if relative.name not in CROSS_CUTTING:
                orphans.append(f"{relative}: a top-level test must cross the whole stack (or move beside its module)")
            continue
        package = REPO.joinpath(*relative.parts[:-1])
        stem = module_of(relative.name)
        candidates = [stem] + [stem.rsplit("_", k)[0] for k in (1, 2) if "_" in stem]
        if not any((package / f"{name}{suffix}").is_file() for name in candidates for suffix in (".py", ".sh")):
            orphans.append(f"{relative}: no module {stem}.py in {package.relative_to(REPO)}")
    assert not orphans, orphans
