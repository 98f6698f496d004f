"""A device wrapper for fault tests: behaves as the wrapped device except where a subclass says."""


class Wrapped:
    """A device that behaves as `inner` except where a subclass says."""

    def __init__(self, inner):
        self.inner = inner

    def __getattr__(self, name):
        return getattr(self.inner, name)
