"""Rate limits for what the pages send: a token bucket, fed with the clock (sans-IO).

A bucket holds at most `burst` tokens and gains `rate` per second; each message takes one.
So a person tapping (a few a second) is never limited, and a flood is cut to `rate` messages a
second after its first `burst`, whatever its speed. Times are integer nanoseconds of the
caller's monotonic clock.
"""

from __future__ import annotations


class TokenBucket:
    def __init__(self, rate: float, burst: int, now: int = 0):
        if not rate > 0 or burst < 1:
            raise ValueError(f'a rate limit needs rate > 0 and burst >= 1, got {rate}, {burst}')
        self.rate = float(rate)
        self.burst = int(burst)
        self.tokens = float(burst)
        self.stamp = int(now)

    def take(self, now: int) -> bool:
        """Whether one more message may pass at `now` (and count it)."""
        elapsed = max(0, int(now) - self.stamp) * 1e-9
        self.stamp = max(self.stamp, int(now))
        self.tokens = min(float(self.burst), self.tokens + elapsed * self.rate)
        if self.tokens >= 1.0:
            self.tokens -= 1.0
            return True
        return False
