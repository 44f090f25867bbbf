"""Generator tests (a package: module names like test_model.py repeat across test folders)."""
