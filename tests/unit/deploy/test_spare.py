"""The supervisor's warm spare (deploy/spare.py): it becomes the module it is given, output in
the given log, arguments as `python -m` gives them; with nothing to become it ends."""
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[3]


def spare():
    return subprocess.Popen([sys.executable, "-m", "deploy.spare"], cwd=ROOT, stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def test_the_spare_runs_the_module_with_its_arguments_into_the_log(tmp_path):
    log = tmp_path / "svc.log"
    log.write_text("--- before ---\n")
    proc = spare()
    job = {"module": "json.tool", "argv": [str(ROOT / "docs" / "foxglove-layout.json"), "--compact"], "log": str(log)}
    said, _ = proc.communicate(json.dumps(job) + "\n", timeout=60)
    assert proc.returncode == 0 and said == "", said
    text = log.read_text()
    assert text.startswith("--- before ---\n")   # appended, as a restart's log is
    assert json.loads(text.split("\n", 1)[1]) == json.loads((ROOT / "docs" / "foxglove-layout.json").read_text())


def test_a_spare_not_needed_ends_when_its_input_closes():
    proc = spare()
    said, _ = proc.communicate("", timeout=60)
    assert proc.returncode == 0 and said == ""
