// `make web`: bundle the player (three.js + Spark + src/) into one ES module inside the Python package, beside
// its page (geoavatar/web/static/index.html, written by hand), so that `pip install` / `make` need no node.
import { build } from "esbuild";
import { mkdirSync, readFileSync } from "node:fs";

// The bundled libraries' MIT notices, whole, at the top of the bundle (their licence asks for it).
const BUNDLED = ["three", "@sparkjsdev/spark", "fflate"];
const notices = BUNDLED.map((name) => {
  const text = readFileSync(new URL(`node_modules/${name}/LICENSE`, import.meta.url), "utf8").replaceAll("*/", "* /");
  return `${name}:\n\n${text.trim()}`;
});
const banner = `/*! GeoAvatar web player (Apache-2.0). Bundled libraries and their licences:\n\n${notices.join("\n\n")}\n*/`;

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
  legalComments: "eof",
  banner: { js: banner },
  logLevel: "warning",
});
console.log(`built ${out.pathname}`);
