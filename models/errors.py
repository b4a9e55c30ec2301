"""The error a model author sees: one line naming the model, the symbol or equation at fault."""


class ModelError(ValueError):
    """A model declaration is inconsistent; the message names the symbol or equation at fault."""
