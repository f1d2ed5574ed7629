"""A stand-in for an application's sound in the tests: a pure tone of HZ as raw
float32 mono 48 kHz on stdout, forever (piped into ``pacat``). Standard library only:
it runs under the system's python3, outside the project's venv."""

import array
import math
import sys

RATE = 48_000
BLOCK = RATE // 50  # 20 ms


def main() -> None:
    hz = float(sys.argv[1])
    step = 2 * math.pi * hz / RATE
    n = 0
    out = sys.stdout.buffer
    while True:
        block = array.array("f", (0.4 * math.sin(step * (n + i)) for i in range(BLOCK)))
        n += BLOCK
        out.write(block.tobytes())
        out.flush()


if __name__ == "__main__":
    main()
