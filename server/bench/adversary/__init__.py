"""``upcast bench adversary``: the relay under attack scenarios, the hostile client
that runs them, and the good viewers that watch meanwhile."""
