"""Entry script a stage's child processes run (see ``party_stage.py``)."""
