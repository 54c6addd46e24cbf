"""Installed like a service (issue 17 item 5): the plugins' own import name, and
`make install` / `make uninstall` into a staged root (DESTDIR).

The staged venv is run through its own interpreter (<root>/usr/lib/lathed/bin/python):
its scripts' #! lines name the final /usr/lib/lathed, which does not exist here.
systemd is not running in a test container, so the units are not started: they are
verified with `systemd-analyze verify` with their paths pointed into the staged root.
"""
from __future__ import annotations

import os
import re
import shutil
import stat
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from lathed import __version__
from tests.conftest import ROOT

LIBDIR = "/usr/lib/lathed"
PROGRAMS = ("lathed", "lathectl", "lathed-web", "lathed-opcua", "lathed-sim")
UNITS = ("lathed.service", "lathed-web.service", "lathed-opcua.service")
CONFIG = ("lathed.toml", "lathed-web.toml", "lathed-opcua.toml", "robot_arm.dbc", "plugins.d/README.md")


# -- the import name, without installing ---------------------------------------------

def test_every_package_folder_is_in_pyproject():
    # explicit packages (find cannot map plugins/ to lathed_plugins): a new folder must be listed
    st = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    assert st["package-dir"]["lathed_plugins"] == "plugins"
    folders = {".".join(p.parent.relative_to(ROOT).parts) for p in (ROOT / "lathed").rglob("__init__.py")}
    assert folders | {"lathed_plugins"} == set(st["packages"])


def test_entry_points_name_lathed_plugins_modules():
    eps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["entry-points"]["lathed.plugins"]
    assert eps
    for name, target in eps.items():
        pkg, _, mod = target.partition(".")
        assert pkg == "lathed_plugins", f"entry point {name} = {target!r}: plugins install as lathed_plugins"
        assert (ROOT / "plugins" / f"{mod}.py").is_file(), f"entry point {name}: no plugins/{mod}.py"


IMPORTS_PLUGINS = re.compile(r"^\s*(from\s+plugins(\.|\s)|import\s+plugins\b)", re.M)


def test_nothing_imports_plugins_by_its_folder_name():
    # `plugins.x` beside `lathed_plugins.x` would be two copies of one module (two classes, two states)
    found = [f"{p.relative_to(ROOT)}:{text[:m.start()].count(chr(10)) + 1}"
             for d in ("lathed", "plugins", "tests", "bench", "etc")
             for p in (ROOT / d).rglob("*.py")
             for text in [p.read_text(encoding="utf-8")] for m in IMPORTS_PLUGINS.finditer(text)]
    assert not found, f"import lathed_plugins.X, not plugins.X: {found}"


def test_the_folder_refuses_its_folder_name(tmp_path):
    r = subprocess.run([sys.executable, "-c", "import plugins"], cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 1
    assert r.stderr.splitlines()[-1] == ("ImportError: import lathed_plugins, not plugins: this folder installs "
                                         "as lathed_plugins")


def test_the_install_lines_name_every_extra():
    # issue 39: the install docs' line left out the mqtt extra
    extras = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]) - {"test"}
    line = next(ln for ln in (ROOT / "docs" / "installation.md").read_text().splitlines()
                if ln.startswith("sudo make install"))
    make = next(ln for ln in (ROOT / "Makefile").read_text().splitlines() if ln.startswith("EXTRAS ?="))
    for where, text in (("docs/installation.md", line), ("Makefile", make)):
        named = set(re.search(r"EXTRAS=([\w,]+)", text)[1].split(","))
        assert named == extras, f"{where}: {text!r} names {sorted(named)}, the extras are {sorted(extras)}"


# -- make install DESTDIR=<root> -------------------------------------------------------

def _make(*args: str, timeout: float = 900) -> subprocess.CompletedProcess:
    return subprocess.run(["make", "-s", *args, f"PY={sys.executable}"], cwd=ROOT, capture_output=True, text=True,
                          timeout=timeout)


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    if shutil.which("make") is None:
        pytest.skip("make not installed")
    root = tmp_path_factory.mktemp("destdir")
    # files left in etc/ that git does not track (an editor's backup, a local config) are not shipped
    stray = [ROOT / "etc" / "untracked-by-test_install.txt", ROOT / "etc" / "plugins.d" / "untracked-by-test_install.txt"]
    for f in stray:
        f.write_text("not part of lathed\n")
    try:
        r = _make("install", f"DESTDIR={root}")
    finally:
        for f in stray:
            f.unlink()
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-4000:]
    return root


def _py(root: Path, *args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTHON", "VIRTUAL_ENV", "LATHED"))}
    return subprocess.run([str(root / LIBDIR.lstrip("/") / "bin" / "python"), *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=120)


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_programs_link_into_the_venv_and_run(root, tmp_path):
    venv_bin = root / LIBDIR.lstrip("/") / "bin"
    for p in PROGRAMS:
        link = root / "usr" / "bin" / p
        assert os.readlink(link) == f"{LIBDIR}/bin/{p}"
        script = venv_bin / p
        assert script.stat().st_mode & stat.S_IXUSR
        assert script.read_text().splitlines()[0] in (f"#!{LIBDIR}/bin/python", f"#!{LIBDIR}/bin/python3",
                                                      f"#!{LIBDIR}/bin/python3.{sys.version_info.minor}")
    for p in ("lathed", "lathectl", "lathed-web"):
        r = _py(root, str(venv_bin / p), "--version", cwd=tmp_path)
        assert (r.returncode, r.stdout.strip()) == (0, f"{p} {__version__}"), r.stderr
    r = _py(root, str(venv_bin / "lathed-sim"), "--help", cwd=tmp_path)
    assert r.returncode == 0 and "usage: lathed-sim" in r.stdout, r.stderr


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_nothing_installed_names_the_staging_root(root):
    # relocated: #! lines, pyvenv.cfg, activate scripts and bytecode's file names say /usr/lib/lathed
    stage = str(root).encode()
    named = [str(p.relative_to(root)) for p in root.rglob("*")
             if p.is_file() and not p.is_symlink() and stage in p.read_bytes()]
    assert not named, named[:10]


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_installed_import_names_and_extras(root, tmp_path):
    code = """
import importlib, importlib.metadata as md, importlib.util as u
import lathed_plugins.chatter
try:
    print("plugins importable from", importlib.import_module("plugins").__file__)
except ModuleNotFoundError:
    pass
print(" ".join(sorted(f"{e.name}={e.value}" for e in md.entry_points(group="lathed.plugins"))))
print(" ".join(m for m in ("psycopg", "matplotlib", "pytest", "hypothesis") if u.find_spec(m)))
print(lathed_plugins.chatter.__file__)
"""
    r = _py(root, "-c", code, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    eps, present, where = r.stdout.split("\n")[:3]
    want = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["entry-points"]["lathed.plugins"]
    assert eps == " ".join(sorted(f"{k}={v}" for k, v in want.items()))
    assert present == "", f"installed without extras, yet {present} is there"
    assert where.startswith(str(root / LIBDIR.lstrip("/") / "lib"))      # the wheel's copy, not the checkout


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_the_mqtt_payload_schemas_are_installed(root):
    # docs/mqtt.md sends a plant to them: they ship in the package, not only in the checkout
    shipped = sorted(p.name for p in (ROOT / "lathed" / "schemas" / "mqtt").glob("*.json"))
    lib = root / LIBDIR.lstrip("/")
    installed = sorted(p.name for p in lib.glob("lib/python3*/site-packages/lathed/schemas/mqtt/*.json"))
    assert shipped == installed == ["event.schema.json", "record.schema.json", "value.schema.json"]


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_installed_config_checks_and_a_missing_extra_is_named(root, tmp_path):
    lathed = str(root / LIBDIR.lstrip("/") / "bin" / "lathed")
    for name in CONFIG:
        assert (root / "etc" / "lathed" / name).read_bytes() == (ROOT / "etc" / name).read_bytes()
    r = _py(root, lathed, "--check-config", str(root / "etc" / "lathed" / "lathed.toml"), cwd=tmp_path)
    # the shipped config and all it names (plugins.d, robot_arm.dbc) are there
    assert r.returncode == 0 and r.stderr == "" and ": ok (" in r.stdout, r.stdout + r.stderr
    cfg = tmp_path / "central.toml"
    cfg.write_text('[analyzer.central]\nplugin = "postgres_sink"\ndsn = "host=db.plant dbname=lathed"\n')
    r = _py(root, lathed, "--check-config", str(cfg), cwd=tmp_path)
    assert r.returncode == 78
    # the service's venv is make install's: pip there is not the way (issue 39)
    assert r.stderr.splitlines() == [f"lathed: {cfg}: [analyzer.central] plugin: the postgres_sink plugin needs "
                                     f"psycopg, which is not installed: in the service's venv ({root / LIBDIR.lstrip('/')}) add it from "
                                     "the lathed source with `sudo make install PREFIX=/usr EXTRAS=postgres`, then "
                                     "`sudo systemctl restart lathed`"]
    # the lathe over OPC UA: its driver and the simulated control's server need the opcua extra
    ua = ROOT / "etc" / "lathed-cell-opcua.toml"
    r = _py(root, lathed, "--check-config", str(ua), cwd=tmp_path)
    extra = (f"cannot run: asyncua is not installed: in the service's venv ({root / LIBDIR.lstrip('/')}) add it "
             "from the lathed source with `sudo make install PREFIX=/usr EXTRAS=opcua`, then "
             "`sudo systemctl restart lathed`")
    assert r.returncode == 78 and r.stderr.splitlines() == [
        f"lathed: {ua}: [machine.lathe] plugin: the opcua_cnc driver {extra}",
        f"lathed: {ua}: [simulator] opcua_port: the simulated control's OPC UA server {extra}"], r.stderr


def _exec_paths(unit: str) -> list[str]:
    return [line.split("=", 1)[1].split()[0] for line in unit.splitlines()
            if line.startswith(("ExecStart=", "ExecStartPre="))]


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_installed_units_point_at_the_venv_and_verify(root, tmp_path):
    units = root / "lib" / "systemd" / "system"
    for name in UNITS:
        text = (units / name).read_text()
        assert "ConfigurationDirectory=lathed\n" in text
        for exe in _exec_paths(text):
            assert exe.startswith(f"{LIBDIR}/bin/"), exe
            assert os.access(root / exe.lstrip("/"), os.X_OK), f"{name}: {exe} is not in the installed tree"
        (tmp_path / name).write_text(text.replace(f"{LIBDIR}/", f"{root}{LIBDIR}/"))
    if shutil.which("systemd-analyze") is None:
        pytest.skip("systemd-analyze not installed")
    for name in UNITS:
        r = subprocess.run(["systemd-analyze", "verify", str(tmp_path / name)], capture_output=True, text=True,
                           cwd=tmp_path)
        assert r.returncode == 0 and r.stdout == "" and r.stderr == "", r.stdout + r.stderr
    r = subprocess.run(["systemd-analyze", "security", "--offline=yes", str(units / "lathed.service")],
                       capture_output=True, text=True)
    m = re.search(r"Overall exposure level for lathed\.service: ([\d.]+)", r.stdout + r.stderr)
    assert m and float(m[1]) <= 2.5, r.stdout + r.stderr


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_sysusers_and_tmpfiles_make_the_users_and_directories(root, tmp_path):
    if shutil.which("systemd-sysusers") is None or shutil.which("systemd-tmpfiles") is None:
        pytest.skip("systemd-sysusers/systemd-tmpfiles not installed")
    if os.geteuid() != 0:
        pytest.skip("systemd-tmpfiles --root needs root to set owners")
    sysroot = tmp_path / "sysroot"
    (sysroot / "etc").mkdir(parents=True)
    r = subprocess.run(["systemd-sysusers", f"--root={sysroot}", str(root / "usr/lib/sysusers.d/lathed.conf")],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    users = {f[0]: f for f in (line.split(":") for line in (sysroot / "etc/passwd").read_text().splitlines())}
    groups = {f[0]: f[3].split(",") for f in (line.split(":") for line in (sysroot / "etc/group").read_text()
                                                                               .splitlines())}
    assert users["lathed"][5:] == ["/var/lib/lathed", "/usr/sbin/nologin"]
    assert users["lathed-web"][6] == "/usr/sbin/nologin"
    assert "lathed" in groups["dialout"] and "lathed-web" in groups["lathed"] and "lathed-opcua" in groups["lathed"]
    shutil.copytree(root / "etc" / "lathed", sysroot / "etc" / "lathed")
    r = subprocess.run(["systemd-tmpfiles", f"--root={sysroot}", "--create",
                        str(root / "usr/lib/tmpfiles.d/lathed.conf")], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    gid = int(users["lathed"][3])
    for path, mode in (("etc/lathed", 0o750), ("etc/lathed/lathed.toml", 0o640), ("var/lib/lathed", 0o750)):
        st = (sysroot / path).stat()
        assert (stat.S_IMODE(st.st_mode), st.st_gid) == (mode, gid), path


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_only_the_files_git_tracks_in_etc_are_installed(root):
    tracked = subprocess.run(["git", "ls-files", "etc"], cwd=ROOT, capture_output=True, text=True).stdout.split()
    examples = root / "usr" / "share" / "doc" / "lathed" / "examples"
    assert sorted(str(p.relative_to(examples)) for p in examples.rglob("*") if p.is_file()) == \
        sorted(f.removeprefix("etc/") for f in tracked)
    assert not list((root / "etc" / "lathed").rglob("untracked-by-test_install.txt"))


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_an_edited_config_is_never_overwritten(root):
    conf = root / "etc" / "lathed"
    edited = (ROOT / "etc" / "lathed.toml").read_text().replace('name = "sim-cell-1"', 'name = "cell-7"')
    (conf / "lathed.toml").write_text(edited)
    (conf / "lathed-web.toml").unlink()
    r = _make("install-config", f"DESTDIR={root}")
    assert r.returncode == 0, r.stderr
    assert (conf / "lathed.toml").read_text() == edited
    assert (conf / "lathed-web.toml").read_bytes() == (ROOT / "etc" / "lathed-web.toml").read_bytes()


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_uninstall_leaves_only_the_config(root):
    # last in this file: it takes the installed tree away
    r = _make("uninstall", f"DESTDIR={root}")
    assert r.returncode == 0, r.stderr
    left = sorted(str(p.relative_to(root)) for p in root.rglob("*") if p.is_file() or p.is_symlink())
    assert left == sorted(f"etc/lathed/{name}" for name in CONFIG)
    assert 'name = "cell-7"' in (root / "etc" / "lathed" / "lathed.toml").read_text()   # the edit stays
