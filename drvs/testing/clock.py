"""A clock that moves only when a test moves it, for the modules that take an injected clock."""


class ManualClock:
    """Monotonic seconds that stand still until a test sets or advances ``now``.

    >>> clock = ManualClock(100.0)
    >>> clock.now += 2.5
    >>> clock()
    102.5
    """

    def __init__(self, now: float = 100.0):
        self.now = now

    def __call__(self) -> float:
        return self.now
