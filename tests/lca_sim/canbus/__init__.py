"""The canbus tests (a package, so that mypy tells its conftest from the top one)."""
