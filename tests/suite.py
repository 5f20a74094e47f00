"""`make test`: every test file runs, in the groups below (each a pytest process of its own), and one summary of them
all is printed at the end, even when a group fails or crashes. Exits 1 if any test failed or any group did not finish.

    python tests/suite.py [pytest options for every group, e.g. -x or -k name]

The serving tests run in a process of their own: after the rest of the suite, a server thread in the same process was
once seen stuck in torch's CPU thread pool (not reproduced since).
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ElementTree
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SERVING = ["tests/test_serving.py", "tests/test_pi0_fast_serving.py"]
GROUPS = {
    "main": ["--doctest-modules", "pi0_torch", "tests", *(f"--ignore={path}" for path in SERVING)],
    "serving": SERVING,
}
COMMON = ["-q", "-p", "no:cacheprovider", "-m", "not slow and not gpu"]


def totals(report: Path) -> tuple[dict[str, int], list[str]]:
    """Counts (tests, failures, errors, skipped) and the failed test ids of a pytest junit-xml report."""
    counts = dict.fromkeys(("tests", "failures", "errors", "skipped"), 0)
    failed = []
    for suite in ElementTree.parse(report).getroot().iter("testsuite"):
        for key in counts:
            counts[key] += int(suite.get(key, 0))
        for case in suite.iter("testcase"):
            if case.find("failure") is not None or case.find("error") is not None:
                failed.append(f"{case.get('classname', '')}::{case.get('name', '')}")
    return counts, failed


def main(extra: list[str]) -> int:
    started = time.monotonic()
    counts = dict.fromkeys(("tests", "failures", "errors", "skipped"), 0)
    failed: list[str] = []
    unfinished = []
    with tempfile.TemporaryDirectory() as folder:
        for name, arguments in GROUPS.items():
            report = Path(folder) / f"{name}.xml"
            print(f"\n== make test: {name} ==", flush=True)
            code = subprocess.call([sys.executable, "-m", "pytest", *COMMON, *arguments, f"--junitxml={report}", *extra], cwd=ROOT)
            if not report.exists():
                unfinished.append(f"{name} (pytest exited {code} without a report)")
                continue
            group_counts, group_failed = totals(report)
            counts = {key: counts[key] + group_counts[key] for key in counts}
            failed += group_failed
            if code not in (0, 1) and not group_failed:  # 1: tests failed; anything else: pytest itself did not finish
                unfinished.append(f"{name} (pytest exited {code})")
    passed = counts["tests"] - counts["failures"] - counts["errors"] - counts["skipped"]
    minutes = (time.monotonic() - started) / 60
    print(f"\n== make test: {passed} passed, {counts['failures'] + counts['errors']} failed, {counts['skipped']} skipped "
          f"in {len(GROUPS)} groups, {minutes:.1f} min ==")
    for test in failed:
        print(f"FAILED {test}")
    for group in unfinished:
        print(f"UNFINISHED {group}")
    return 1 if failed or unfinished else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
