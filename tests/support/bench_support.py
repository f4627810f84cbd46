"""What the benchmark tests share: the checkout on sys.path (bench/ is a
package of the checkout, not of the install), and the numbers of a JSON tree."""
from __future__ import annotations

import sys
import places

ROOT = places.REPO
if str(ROOT) not in sys.path:  # `python -m pytest` puts it there; plain `pytest` does not
    sys.path.insert(0, str(ROOT))


def json_numbers(value, path: str = "result"):
    """Every number in a JSON tree, with where it is."""
    if isinstance(value, dict):
        for key, item in value.items():
            yield from json_numbers(item, f"{path}.{key}")
    elif isinstance(value, list):
        for i, item in enumerate(value):
            yield from json_numbers(item, f"{path}[{i}]")
    elif isinstance(value, (int, float)) and not isinstance(value, bool):
        yield path, value


def spreads(value, path: str = "result"):
    """Every {median, min, max} in a JSON tree, with where it is."""
    if isinstance(value, dict):
        if set(value) == {"median", "min", "max"}:
            yield path, value
            return
        for key, item in value.items():
            yield from spreads(item, f"{path}.{key}")
    elif isinstance(value, list):
        for i, item in enumerate(value):
            yield from spreads(item, f"{path}[{i}]")


def check_json(written: dict) -> None:
    """Every number finite, every {median, min, max} in order."""
    import math
    for where, number in json_numbers(written):
        assert math.isfinite(number), where
    for where, s in spreads(written):
        assert 0 <= s["min"] <= s["median"] <= s["max"], (where, s)
