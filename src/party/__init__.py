"""party: a training platform for part-aware text-to-motion synthesis.

    import party
    motions = party.load("data/generators/party").generate(["a person waves"], frames=60)
"""
__version__ = "0.1.0"


def load(source=None, *, params=None):
    """A trained generator, ready to ``generate`` (``party.api.load``)."""
    from party.api import load as _load
    return _load(source, params=params)
