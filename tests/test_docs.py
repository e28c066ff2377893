"""The code in docs/policies.md runs as written."""

import json
import re
import sys
import types
from pathlib import Path

DOC = Path(__file__).resolve().parents[1] / "docs" / "policies.md"


def test_policy_example_in_docs_runs(tmp_path):
    code = "\n".join(re.findall(r"```python\n(.*?)```", DOC.read_text(), flags=re.S))
    module = types.ModuleType("policies_doc_example")
    module.OUT_DIR = str(tmp_path)
    sys.modules[module.__name__] = module  # the example registers "<module>:LiftPolicy"
    exec(compile(code, str(DOC), "exec"), module.__dict__)
    lines = [json.loads(line) for line in (tmp_path / "episodes.jsonl").read_text().splitlines()]
    assert len(lines) == 2 and all(r["steps"] == 15 for r in lines)
    assert next(r for r in lines if r["method"] == "lift")["summary"] == {"steps": 15}
