"""The live view and the operator's station: the ``display`` node and its server."""

from .display import Display as Display
