"""Tests mirror the modules they test: ``tests/<package path>/test_<module>[_<aspect>].py`` tests
``<package path>/<module>.py`` (or a script, ``.sh``; a deployment file, ``.yaml`` with ``-`` for ``_``; a folder of
them, such as deploy/systemd; ``test_main`` tests ``__main__.py``); at the top of tests/ only the tests that cross
the whole stack."""
from tests.helpers import REPO

CROSS_CUTTING = {"test_imports.py", "test_latency.py", "test_fuzz_services.py", "test_shipped_configs.py", "test_overload.py",
                 "test_layout.py", "test_docs.py"}


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
        files = [package / f"{name}{suffix}" for name in candidates for suffix in (".py", ".sh")]
        files += [package / f"{name.replace('_', '-')}.yaml" for name in candidates]
        if not any(f.is_file() for f in files) and not any((package / name).is_dir() for name in candidates):
            orphans.append(f"{relative}: no module {stem}.py in {package.relative_to(REPO)}")
    assert not orphans, orphans
