// `make web`: bundle the player (three.js + Spark + src/) into one ES module inside the Python package,
// beside the page, so that `pip install` / `make` need no node.
import { build } from "esbuild";
import { copyFileSync, mkdirSync } from "node:fs";

const out = new URL("../geoavatar/web/static/", import.meta.url);
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
copyFileSync(new URL("index.html", import.meta.url), new URL("index.html", out));
console.log(`built ${out.pathname}`);
