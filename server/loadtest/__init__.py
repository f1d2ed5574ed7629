"""``upcast loadtest``: many moq-lite viewers against a relay, measured."""
