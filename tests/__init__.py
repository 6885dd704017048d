"""ddrt's tests. A package, so that pytest puts the repository root on sys.path and every shared
helper is imported one way: `from tests.support.<module> import ...` (tests/support/)."""
