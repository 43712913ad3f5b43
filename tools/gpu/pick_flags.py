"""Picks the XLA flag set for the lanes from flags.sh's JSON rows (one file per flag set).

A flag set is taken over XLA's default only if it is faster in every row (each learner and
variant) and at least 10% faster in the geometric mean; prints the chosen XLA_FLAGS value.
Usage: python tools/gpu/pick_flags.py DEFAULT.json 'FLAGS' OTHER.json ...
"""

import json
import math
import sys


def rows(path: str) -> dict[tuple[str, str], float]:
    out = {}
    with open(path) as f:
        for line in f:
            if line.startswith("{"):
                row = json.loads(line)
                out[(row["algo"], row["variant"])] = row["env_steps_per_s"]
    return out


def main(argv: list[str]) -> int:
    base = rows(argv[0])
    best, best_gain = "", 1.0
    for flags, path in zip(argv[1::2], argv[2::2], strict=True):
        other = rows(path)
        ratios = [other[k] / base[k] for k in base if k in other]
        if not ratios or len(ratios) < len(base):
            print(f"# {flags!r}: incomplete", file=sys.stderr)
            continue
        gain = math.exp(sum(map(math.log, ratios)) / len(ratios))
        print(f"# {flags!r}: speed x{gain:.2f} (rows {min(ratios):.2f}-{max(ratios):.2f})",
              file=sys.stderr)
        if min(ratios) > 1.0 and gain >= 1.1 and gain > best_gain:
            best, best_gain = flags, gain
    print(best)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
