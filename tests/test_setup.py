"""Importing jaxcal turns on float64 and leaves the persistent compilation cache off unless asked."""

import os
import subprocess
import sys

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SHOW = "import jax, jaxcal; print(jax.config.jax_enable_x64, jax.config.jax_compilation_cache_dir)"


def run_python(code: str, tmp_path, **env) -> str:
    """stdout of `python -c code` in a fresh process with HOME in tmp_path and no JAXCAL_CACHE unless given."""
    clean = {k: v for k, v in os.environ.items() if k != "JAXCAL_CACHE"}
    clean |= {"HOME": str(tmp_path), "PYTHONPATH": REPO, **env}
    done = subprocess.run([sys.executable, "-c", code], env=clean, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return done.stdout.strip()


def test_import_leaves_the_cache_off(tmp_path):
    assert run_python(SHOW, tmp_path) == "True None"
    assert not (tmp_path / ".cache").exists()


def test_jaxcal_cache_names_the_folder(tmp_path):
    folder = tmp_path / "xla"
    assert run_python(SHOW, tmp_path, JAXCAL_CACHE=str(folder)) == f"True {folder}"
    assert run_python(SHOW, tmp_path, JAXCAL_CACHE="1") == f"True {tmp_path / '.cache' / 'jaxcal' / 'xla'}"


def test_cli_cache_option_fills_the_folder(tmp_path):
    folder = tmp_path / "xla"
    code = ("from jaxcal.cli import main; "
            f"main(['--cache', {str(folder)!r}, 'simulate', 'mrr1', '--n', '5', '--out', {str(tmp_path / 's.csv')!r}])")
    run_python(code, tmp_path)
    assert any(folder.iterdir())
