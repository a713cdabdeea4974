"""The tests, laid out like the package (tests/<subsystem>/); shared helpers in tests/support/."""
