"""``python -m mst.eval.bench --out bench-results.json`` (``make bench``): every stage's benchmark."""

import sys

from mst.eval.bench.harness import main

sys.exit(main())
