"""Score a twin study trial against the twin's truth: ``python scripts/twin_check.py results/sheep1``."""

import json
import sys

from bsipipe.synth.check import format_check, twin_check

if __name__ == "__main__":
    if len(sys.argv) < 2 or sys.argv[1] in ("-h", "--help"):
        sys.exit(__doc__)
    for d in sys.argv[1:]:
        c = twin_check(d)
        print(f"{d}\n{format_check(c)}")
        if "--json" in sys.argv:
            print(json.dumps(c, indent=1))
