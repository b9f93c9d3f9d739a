"""``python -m testbed OUT [SET ...]`` (from ``benchmarks/``): write the generator's sets."""

import sys
from pathlib import Path

from .sets import SETS, ensure_set, ict_tarball

if __name__ == "__main__":
    out = Path(sys.argv[1])
    for name in sys.argv[2:] or SETS:
        print(name, ensure_set(ict_tarball(), out, name), flush=True)
