"""t42_transfer: transfer learned dynamics models between Yale Model-T42 hands."""

__version__ = "0.1.0"
