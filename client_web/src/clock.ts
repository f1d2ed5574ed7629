// Wall-clock time as the server stamps it (microseconds since the Unix epoch).
// performance.timeOrigin + performance.now() is monotonic within the page and still
// comparable with the server's time.time_ns() when both machines are NTP-synced;
// Date.now() would be ms-granular and can jump.

/** Wall clock in milliseconds (float), the unit of the input `sent_ms`. */
export function wallMs(): number {
	return performance.timeOrigin + performance.now();
}

/** Wall clock in integer microseconds, the unit of the timing track's stamps. */
export function wallUs(): number {
	return Math.round(wallMs() * 1000);
}
