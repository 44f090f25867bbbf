"""party: training platform for ParTY."""
__version__ = "0.1.0"
