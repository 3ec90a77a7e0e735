"""Where the tests find the repository, their stored data and the real capture (whichever tier they are in)."""

from pathlib import Path

TESTS = Path(__file__).resolve().parent
REPO = TESTS.parent
# Golden images and other small files the tests compare against.
TEST_DATA = TESTS / "data"
# The real capture beside the repository (../shared/data/beer); tests that need it skip without it.
BEER = REPO.parent / "shared" / "data" / "beer"
