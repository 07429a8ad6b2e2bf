"""The import direction between packages: service -> drivers, registration, schemas; never back."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
IO_LIBRARIES = {"zenoh", "fastapi", "mcap", "mcap_protobuf", "pynetdicom", "uvicorn", "pydicom", "nibabel"}


def imports_of(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
    return names


def python_files(folder: str) -> list[Path]:
    return sorted((ROOT / folder).rglob("*.py"))


@pytest.mark.parametrize("folder", ["registration", "drivers", "schemas"])
def test_nothing_imports_service(folder):
    offenders = [str(p.relative_to(ROOT)) for p in python_files(folder) if any(n.startswith("drillnav.service") for n in imports_of(p))]
    assert offenders == []


def test_registration_is_pure():
    offenders = {
        str(p.relative_to(ROOT)): sorted(n for n in imports_of(p) if n.split(".")[0] in IO_LIBRARIES or n.startswith("drillnav.drivers"))
        for p in python_files("registration")
    }
    assert {k: v for k, v in offenders.items() if v} == {}


def test_every_package_folder_is_found():
    assert len(python_files("registration")) >= 6
