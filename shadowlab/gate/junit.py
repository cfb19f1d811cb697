"""JUnit XML of gate results: one ``<testcase>`` per check (classname = the gate, name = the check),
a ``<failure>`` with the check's line when it failed. Written atomically.

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


def junit_xml(results, suite: str = "gates", time_s: float = 0.0) -> str:
    n = sum(len(r.checks) for r in results)
    nf = sum(not c.passed for r in results for c in r.checks)
    root = ET.Element("testsuites", {"name": "shadowlab gate", "tests": str(n), "failures": str(nf), "errors": "0",
                                     "time": f"{time_s:.3f}"})
    ts = ET.SubElement(root, "testsuite", {"name": suite, "tests": str(n), "failures": str(nf), "errors": "0",
                                           "skipped": "0", "time": f"{time_s:.3f}"})
    for r in results:
        per = float(r.info.get("time_s", 0.0)) / max(len(r.checks), 1)
        for c in r.checks:
            tc = ET.SubElement(ts, "testcase", {"classname": r.name, "name": c.name, "time": f"{per:.3f}"})
            if not c.passed:
                f = ET.SubElement(tc, "failure", {"message": c.line(r.name), "type": c.kind})
                f.text = "\n".join([c.line(r.name)] + [f"{k}: {v}" for k, v in r.info.items()
                                                       if k in ("scene", "candidate", "reference", "description") and v])
            else:
                so = ET.SubElement(tc, "system-out")
                so.text = c.line(r.name)
    ET.indent(root)
    return '<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


def write_junit(path, results, suite: str = "gates", time_s: float = 0.0):
    p = write_bytes_atomic(path, junit_xml(results, suite, time_s).encode("utf-8"))
    os.chmod(p, 0o644)
    return p
