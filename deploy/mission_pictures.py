"""The mission report's page: OUT/report/index.html with the summary's tables (pictures to follow)."""

import html
import json
import os


def write_report(out, summary):
    report = os.path.join(out, "report")
    os.makedirs(report, exist_ok=True)
    with open(os.path.join(report, "index.html"), "w") as f:
        f.write("<!doctype html><meta charset='utf-8'><title>cvislam mission</title>")
        f.write("<h1>cvislam mission</h1><pre>")
        f.write(html.escape(json.dumps(summary, indent=2)))
        f.write("</pre>")
