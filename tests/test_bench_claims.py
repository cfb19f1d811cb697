"""The sources' figures beside the measured ones (:mod:`shadowlab.bench.claims`): every claim finds
its measurement in each machine's latest committed run record, so the docs' table has no gap.
What the ratios are is never asserted; the examples of the module run as doctests."""

from shadowlab.bench.claims import CLAIMS, latest_by_machine, measured
from shadowlab.bench.record import load_records
from shadowlab.docs import DOCS


def test_every_claim_is_measured_in_each_machines_latest_record():
    records = load_records(DOCS / "bench" / "runs")
    for c in CLAIMS:
        latest = latest_by_machine(records, c.part)
        assert latest, f"no committed record of bench part {c.part!r}"
        for label, rec in latest.items():
            values = measured(c, rec)
            assert values and all(v > 0 for v in values), (c.what, label, rec["file"])
