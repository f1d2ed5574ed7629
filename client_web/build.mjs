// Bundles the player and the @moq/watch interop page into dist/ with esbuild.
// Why a script and not the CLI: two entry points plus static files, one command, and
// `--watch` for development; no other tooling (no tsc: esbuild strips the types).
import { cpSync, mkdirSync, rmSync } from "node:fs";
import { dirname, join } from "node:path";
import { fileURLToPath } from "node:url";
import * as esbuild from "esbuild";

const root = dirname(fileURLToPath(import.meta.url));
const dist = join(root, "dist");
const watch = process.argv.includes("--watch");

rmSync(dist, { recursive: true, force: true });
mkdirSync(dist, { recursive: true });
for (const file of ["index.html", "watch.html", "style.css"]) {
	cpSync(join(root, "static", file), join(dist, file));
}
// The loopback test page (tests/browser): the player wired to an in-page publisher.
mkdirSync(join(dist, "test"));
cpSync(join(root, "test", "loopback.html"), join(dist, "test", "loopback.html"));

const options = {
	entryPoints: {
		player: join(root, "src/player.ts"),
		watch: join(root, "src/watch.ts"),
		"test/loopback": join(root, "test/loopback.ts"),
	},
	outdir: dist,
	bundle: true,
	format: "esm",
	// WebTransport + WebCodecs browsers only; es2022 keeps class private fields native.
	target: "es2022",
	platform: "browser",
	sourcemap: true,
	minify: !watch,
	logLevel: "info",
	// Keep console output: the page logs connect/disconnect on purpose.
	legalComments: "none",
};

if (watch) {
	const ctx = await esbuild.context(options);
	await ctx.watch();
} else {
	await esbuild.build(options);
}
