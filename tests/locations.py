"""Where the tests find the repository, their stored data and the real capture (whichever tier they are in)."""

import os
from pathlib import Path

TESTS = Path(__file__).resolve().parent
REPO = TESTS.parent
# Golden images and other small files the tests compare against.
TEST_DATA = TESTS / "data"
#: The variable that names the folder holding the real capture (``beer/``), wherever it is.
REAL_DATA_ENV = "PATEXGS_REAL_DATA"
# The real capture: $PATEXGS_REAL_DATA/beer, else beside the repository (../shared/data/beer);
# tests that need it skip without it.
REAL_DATA = Path(os.environ.get(REAL_DATA_ENV) or REPO.parent / "shared" / "data")
BEER = REAL_DATA / "beer"
