"""A wall clock the test sets by hand, for simulated drives on a clock of their own (``clock=``)."""


class FakeClock:
    """Reads ``now`` [s]; the test moves it."""

    def __init__(self, now: float = 100.0) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now
