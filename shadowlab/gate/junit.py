"""JUnit XML of gate results: one ``<testcase>`` per check (classname = the gate, name = the check),
a ``<failure>`` with the check's line when it failed. Written atomically.

An interrupted run (SIGINT / SIGTERM) is never written as a success: ``interrupted`` adds a
testcase ``shadowlab gate / interrupted`` with an ``<error>`` (``errors="1"``), so CI reads it red.

>>> from shadowlab.gate.check import Check, GateResult
>>> r = GateResult("contact/pcss", "shaded", [Check("budget.flip", "budget", 0.2, 0.1, "<=", False, "0.2 <= 0.1")])
>>> print(junit_xml([r], suite="gates").splitlines()[1])
<testsuites name="shadowlab gate" tests="1" failures="1" errors="0" time="0.000">
"""

from __future__ import annotations

import os
import xml.etree.ElementTree as ET

from ..io.png import write_bytes_atomic

__all__ = ["junit_xml", "write_junit"]


def junit_xml(results, suite: str = "gates", time_s: float = 0.0, interrupted: str | None = None) -> str:
    n = sum(len(r.checks) for r in results) + (1 if interrupted else 0)
    nf = sum(not c.passed for r in results for c in r.checks)
    ne = "1" if interrupted else "0"
    root = ET.Element("testsuites", {"name": "shadowlab gate", "tests": str(n), "failures": str(nf), "errors": ne,
                                     "time": f"{time_s:.3f}"})
    ts = ET.SubElement(root, "testsuite", {"name": suite, "tests": str(n), "failures": str(nf), "errors": ne,
                                           "skipped": "0", "time": f"{time_s:.3f}"})
    if interrupted:
        tc = ET.SubElement(ts, "testcase", {"classname": "shadowlab gate", "name": "interrupted", "time": "0.000"})
        e = ET.SubElement(tc, "error", {"message": interrupted, "type": "interrupted"})
        e.text = interrupted
    for r in results:
        per = float(r.info.get("time_s", 0.0)) / max(len(r.checks), 1)
        for c in r.checks:
            tc = ET.SubElement(ts, "testcase", {"classname": r.name, "name": c.name, "time": f"{per:.3f}"})
            if not c.passed:
                f = ET.SubElement(tc, "failure", {"message": c.line(r.name), "type": c.kind})
                f.text = "\n".join(
                    [c.line(r.name)]
                    + [
                        f"{k}: {v}"
                        for k, v in r.info.items()
                        if k in ("scene", "candidate", "reference", "description") and v
                    ]
                )
            else:
                so = ET.SubElement(tc, "system-out")
                so.text = c.line(r.name)
    ET.indent(root)
    return '<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


def write_junit(path, results, suite: str = "gates", time_s: float = 0.0, interrupted: str | None = None):
    p = write_bytes_atomic(path, junit_xml(results, suite, time_s, interrupted).encode("utf-8"))
    os.chmod(p, 0o644)
    return p
