"""docs/installation.md's wheel, built and installed for real, as a user on another machine would.

The wheel is built from the clone (``pip wheel --no-deps``, with no build isolation: hatchling
comes from the dev extra, so no network is needed) and installed into a new virtual environment.
That environment gets its dependencies (websockets, pydantic, PyYAML) from this one's
site-packages through a ``.pth`` line: such a path is searched after the environment's own
site-packages, and the ``.pth`` files inside it are not processed, so the editable install of
srvwire there is invisible and only the wheel's srvwire can answer. The commands then run from
a folder outside the clone, as they would on a robot.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import sysconfig
import tomllib
import zipfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

import srvwire
from support import ROOT, scaled


@dataclass(frozen=True)
class Installed:
    wheel: Path
    venv: Path
    cwd: Path  # an empty folder outside the clone

    def run(self, *argv: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            argv,
            cwd=self.cwd,
            env={"PATH": f"{self.venv / 'bin'}:/usr/bin:/bin"},
            capture_output=True,
            text=True,
            timeout=scaled(60),
            check=False,
        )


def pip(*argv: str) -> None:
    result = subprocess.run(
        [sys.executable, "-m", "pip", "--disable-pip-version-check", *argv],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=scaled(120),
        check=False,
    )
    assert result.returncode == 0, result.stdout + result.stderr


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Installed]:
    root = tmp_path_factory.mktemp("install")
    dist = root / "dist"
    pip("wheel", "--no-deps", "--no-build-isolation", "--no-index", ".", "-w", str(dist))
    [wheel] = dist.glob("srvwire-*.whl")
    venv = root / "venv"
    subprocess.run(
        [sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=60
    )
    [site] = venv.glob("lib/python*/site-packages")
    here = sysconfig.get_paths()
    folders = dict.fromkeys([here["purelib"], here["platlib"]])  # the same folder in a venv
    (site / "dependencies.pth").write_text("".join(f"{folder}\n" for folder in folders))
    target = ("--python", str(venv / "bin" / "python"))
    # By its path: named as "srvwire", pip would see this venv's editable srvwire through the
    # .pth line and call it already installed.
    pip(*target, "install", "--no-deps", "--no-index", str(wheel))
    cwd = root / "elsewhere"
    cwd.mkdir()
    yield Installed(wheel, venv, cwd)


def test_the_wheel_holds_the_package_and_the_interface_files(installed: Installed) -> None:
    # Pure Python, the name docs/installation.md shows: one file for every platform.
    assert installed.wheel.name == f"srvwire-{srvwire.__version__}-py3-none-any.whl"
    with zipfile.ZipFile(installed.wheel) as wheel:
        names = wheel.namelist()
    assert "srvwire/__init__.py" in names
    assert "srvwire/py.typed" in names
    bundled = ROOT / "interfaces"
    expected = {
        f"srvwire/interfaces/{path.relative_to(bundled).as_posix()}"
        for path in bundled.rglob("*")
        if path.is_file()
    }
    assert expected and expected <= set(names)
    assert not [name for name in names if name.startswith(("tests/", "examples/", "docs/"))]


def test_the_installed_command_prints_its_version(installed: Installed) -> None:
    result = installed.run("srvwire", "--version")
    assert (result.returncode, result.stdout, result.stderr) == (
        0,
        f"srvwire {srvwire.__version__}\n",
        "",
    )


def test_the_installed_command_lists_the_bundled_interfaces(installed: Installed) -> None:
    result = installed.run("srvwire", "interface", "list")
    assert result.returncode == 0, result.stderr
    for name in ("example_interfaces/srv/AddTwoInts", "std_srvs/srv/Trigger"):
        assert name in result.stdout


def test_the_installed_package_loads_a_bundled_type_from_the_wheel(installed: Installed) -> None:
    code = (
        "import srvwire, srvwire.loader\n"
        "AddTwoInts = srvwire.load_service('example_interfaces/srv/AddTwoInts')\n"
        "print(srvwire.__file__)\n"
        "print(srvwire.loader.bundled_interfaces())\n"
        "print(AddTwoInts.Request(a=2, b=3))\n"
    )
    result = installed.run("python", "-c", code)
    assert result.returncode == 0, result.stderr
    package, interfaces, request = result.stdout.splitlines()
    # Both from the wheel, not from the clone's src/ and interfaces/.
    assert Path(package).is_relative_to(installed.venv)
    assert Path(interfaces).is_relative_to(installed.venv)
    assert (Path(interfaces) / "example_interfaces" / "srv" / "AddTwoInts.srv").is_file()
    assert request == "a=2 b=3"


def test_the_readme_is_the_wheels_description(installed: Installed) -> None:
    with zipfile.ZipFile(installed.wheel) as wheel:
        [name] = [name for name in wheel.namelist() if name.endswith(".dist-info/METADATA")]
        metadata = wheel.read(name).decode()
    headers, _, description = metadata.partition("\n\n")
    assert "Description-Content-Type: text/markdown" in headers.splitlines()
    assert description.strip() == (ROOT / "README.md").read_text(encoding="utf-8").strip()


def test_the_readme_reads_on_a_package_index() -> None:
    # It opens with the two commands; its links work where the description is shown away from
    # the repository (an index page): every one is absolute, none points into the clone.
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    assert readme.startswith("# srvwire\n\n```sh\nmake demo   # ")
    assert readme.split("```")[1].splitlines()[2].startswith("make test   # ")
    targets = re.findall(r"\]\(([^)]+)\)", readme) + re.findall(r"^\[[^]]+\]:\s*(\S+)", readme)
    assert targets
    assert [target for target in targets if not target.startswith("https://")] == []


def test_the_installation_page_names_this_version() -> None:
    page = (ROOT / "docs" / "installation.md").read_text(encoding="utf-8")
    version = srvwire.__version__
    assert set(re.findall(r"srvwire-[\w.]+-py3-none-any\.whl", page)) == {
        f"srvwire-{version}-py3-none-any.whl"
    }
    assert f"srvwire --version          # srvwire {version}\n" in page


def test_the_supported_pythons_agree_everywhere() -> None:
    # pyproject's requires-python and classifiers, the Makefile's guard, and the pages that tell
    # a user which Python to bring all name the same versions: the oldest, and every one.
    project = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    classifiers = " ".join(project["classifiers"])
    listed = re.findall(r"Programming Language :: Python :: (3\.\d+)\b", classifiers)
    assert listed, "pyproject.toml lists no Python version among its classifiers"
    oldest = listed[0]
    assert project["requires-python"] == f">={oldest}"
    major, minor = oldest.split(".")
    makefile = (ROOT / "Makefile").read_text(encoding="utf-8")
    assert f"sys.version_info < ({major}, {minor})" in makefile
    assert f'"srvwire needs Python {oldest} or newer"' in makefile
    for page in ("README.md", "docs/index.md", "docs/installation.md"):
        text = " ".join((ROOT / page).read_text(encoding="utf-8").split())
        assert f"Python {oldest} or newer" in text, page
    installation = " ".join((ROOT / "docs" / "installation.md").read_text(encoding="utf-8").split())
    [runs_on] = re.findall(r"srvwire runs on Python ([\d., and]+?),? and their", installation)
    assert re.split(r",? and |, ", runs_on.strip()) == listed


def make_pytest(*assignments: str) -> list[str]:
    """The commands ``make pytest`` would run with ``assignments`` (a dry run: nothing runs),
    whatever the make that runs this suite was given (``make test PYTEST_WORKERS=0``)."""
    inherited = {"MAKEFLAGS", "MFLAGS", "MAKELEVEL", "PYTEST_WORKERS"}
    result = subprocess.run(
        ["make", "--dry-run", "pytest", *assignments],
        cwd=ROOT,
        env={name: value for name, value in os.environ.items() if name not in inherited},
        capture_output=True,
        text=True,
        timeout=scaled(60),
        check=False,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    return result.stdout.splitlines()


def test_make_runs_the_tests_on_every_core_and_pytest_alone_in_one_process() -> None:
    # docs/installation.md: make asks for the workers (each file on one, so that a module's
    # fixtures are made once); pytest's own options do not, so a file run by hand starts none.
    command = ".venv/bin/pytest -n {} --dist loadfile --no-loadscope-reorder"
    assert command.format("auto") in make_pytest()
    assert command.format(0) in make_pytest("PYTEST_WORKERS=0")
    options = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["tool"]
    assert not re.search(
        r"(^|\s)(-n|--numprocesses|--dist)\b", options["pytest"]["ini_options"]["addopts"]
    )
