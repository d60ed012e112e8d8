"""The one error type of the strategies."""


class StrategyError(ValueError):
    """A strategy was configured or called in a way it cannot work with."""
