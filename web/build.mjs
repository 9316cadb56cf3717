// `make web`: bundle the player (three.js + Spark + src/) into one ES module inside the Python package, beside
// its page (geoavatar/web/static/index.html, written by hand), so that `pip install` / `make` need no node.
import { build } from "esbuild";
import { mkdirSync } from "node:fs";

// GEOAVATAR_WEB_OUT: another folder (tests/test_web_binding.py checks that the committed bundle is current)
const out = process.env.GEOAVATAR_WEB_OUT
  ? new URL(`file://${process.env.GEOAVATAR_WEB_OUT.replace(/\/?$/, "/")}`)
  : new URL("../geoavatar/web/static/", import.meta.url);
mkdirSync(out, { recursive: true });
await build({
  entryPoints: [new URL("src/player.js", import.meta.url).pathname],
  outfile: new URL("player.js", out).pathname,
  bundle: true,
  format: "esm",
  minify: true,
  target: "es2020",
  legalComments: "eof", // three.js and Spark are MIT: their notices stay in the bundle
  logLevel: "warning",
});
console.log(`built ${out.pathname}`);
