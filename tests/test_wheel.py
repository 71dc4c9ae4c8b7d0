"""A regular (non-editable) install works: build the wheel, install it into a fresh venv and run
``fr`` from a folder outside the repository.

Dependencies are not downloaded again: the venv sees the running interpreter's site-packages
through a ``.pth`` file, and the wheel itself is installed with ``--no-deps``.
"""
import importlib.util
import json
import os
import shutil
import site
import subprocess
import sys
import venv
import zipfile
from pathlib import Path

from tests.conftest import REPO

SOURCES = ("pyproject.toml", "README.md", "fr_torch", "configs", "eval", "baselines")


def _run(cmd, **kwargs):
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=240, **kwargs)
    assert out.returncode == 0, f"{cmd}: {out.stdout[-2000:]}\n{out.stderr[-2000:]}"
    return out


def test_wheel_installs_and_runs_from_any_folder(tmp_path):
    # Build from a copy, so the checkout gets no build/ or egg-info folders.
    src = tmp_path / "src"
    src.mkdir()
    for name in SOURCES:
        path = REPO / name
        if path.is_dir():
            shutil.copytree(path, src / name, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
        else:
            shutil.copy2(path, src / name)
    isolation = [] if importlib.util.find_spec("setuptools") is None else ["--no-build-isolation"]
    _run([sys.executable, "-m", "pip", "wheel", "--no-deps", *isolation, "-q", "-w", str(tmp_path / "dist"),
          str(src)])
    (wheel,) = (tmp_path / "dist").glob("fr_torch-*.whl")
    # project-specific top-level packages only: eval/ and baselines/ install as fr_eval and fr_baselines
    top_level = {name.split("/")[0] for name in zipfile.ZipFile(wheel).namelist() if "/" in name}
    assert {"fr_torch", "fr_eval", "fr_baselines"} <= top_level and not {"eval", "baselines"} & top_level, top_level

    env_dir = tmp_path / "venv"
    venv.EnvBuilder(with_pip=False).create(env_dir)
    python = env_dir / ("Scripts/python.exe" if os.name == "nt" else "bin/python")
    purelib = Path(_run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"])
                   .stdout.strip())
    # The running interpreter's dependency folders (its site-packages and any they chain to by .pth).
    shared = list(dict.fromkeys(p for p in [*site.getsitepackages(), *sys.path]
                                if p.endswith("site-packages") and Path(p).is_dir()))
    (purelib / "zz_shared_dependencies.pth").write_text("\n".join(shared) + "\n")
    # pip (seen through the .pth) installs into the interpreter running it: the venv.  --ignore-installed:
    # never uninstall a copy that the shared site-packages holds (an editable install, in CI).
    _run([str(python), "-m", "pip", "install", "--no-deps", "--ignore-installed", "--no-warn-script-location",
          "-q", str(wheel)])

    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    work = tmp_path / "elsewhere"
    work.mkdir()
    fr = env_dir / ("Scripts/fr.exe" if os.name == "nt" else "bin/fr")
    # Four commands from elsewhere, run side by side (each is one process of its own): one python
    # process says which fr_torch it imports, the methods its entry points register and which packages
    # it finds (fr_eval ... installed; the folder names eval, baselines not); fr --help;
    # python -m fr_eval --help; fr calibrate.
    commands = {
        "probe": [str(python), "-c", "import importlib.util as u, fr_torch; print(fr_torch.__file__); "
                  "from fr_torch.plugins.interface import available_methods as m; print(m()); "
                  "print([u.find_spec(n) is not None for n in ('fr_eval', 'fr_eval.datasets', 'fr_eval.protocols', "
                  "'fr_eval.bench', 'fr_eval.scoring', 'fr_baselines', 'eval', 'baselines')])"],
        "help": [str(fr), "--help"],
        "eval_help": [str(python), "-m", "fr_eval", "--help"],
        "calibrate": [str(fr), "calibrate", "--fast", str(REPO / "examples" / "room.png")],
    }
    running = {name: subprocess.Popen(cmd, cwd=work, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
               for name, cmd in commands.items()}
    done = {}
    try:
        for name, process in running.items():
            stdout, stderr = process.communicate(timeout=240)
            assert process.returncode == 0, f"{commands[name]}: {stdout[-2000:]}\n{stderr[-2000:]}"
            done[name] = stdout
    finally:
        for process in running.values():
            if process.poll() is None:
                process.kill()
                process.wait()
    where, methods, found = done["probe"].strip().splitlines()[-3:]
    assert str(env_dir) in where, where  # the wheel's copy, not the checkout
    for command in ("calibrate", "track", "eval", "train-reliability", "bench"):  # harness: via entry points
        assert command in done["help"]
    assert "lee2009" in methods  # baselines registered through the fr_torch.calibrators entry point
    assert found.strip() == "[True, True, True, True, True, True, False, False]", found
    assert "train-reliability" in done["eval_help"]
    record = json.loads(done["calibrate"].strip().splitlines()[0])
    assert record["ok"] and abs(record["focal_px"] - 420) < 15
    assert record["predicted_error"] is not None  # the shipped reliability model was found
