"""The one error of the export: a model the header cannot carry (no imports of the package)."""

__all__ = ['ExportError']


class ExportError(ValueError):
    """A model the header cannot carry: the message says why and what to do."""
