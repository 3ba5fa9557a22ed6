"""What the tests spent their time on, from pytest's JUnit report (``make test`` writes
``.test-report.xml``): the total, the time per test file and the 30 slowest tests.  CI
prints it after the book is built, so the last lines of a CI log say where its time went."""

import sys
import xml.etree.ElementTree as ET
from collections import Counter

report = ET.parse(sys.argv[1] if len(sys.argv) > 1 else ".test-report.xml")
cases = [
    (float(c.get("time", 0)), f"{c.get('classname', '')}::{c.get('name', '')}")
    for c in report.iter("testcase")
]
per_file = Counter()
for seconds, name in cases:
    per_file[name.split("::")[0]] += seconds
print(f"tests: {len(cases)}, {sum(s for s, _ in cases):.0f} s of worker time")
print("by file (s):")
for name, seconds in per_file.most_common(12):
    print(f"  {seconds:7.1f}  {name}")
print("the 30 slowest tests (s):")
for seconds, name in sorted(cases, reverse=True)[:30]:
    print(f"  {seconds:7.1f}  {name}")
