// Generate schema.d.ts from openapi.yaml (node generate.mjs OPENAPI_YAML OUT): openapi-typescript's
// documented transform types `format: binary` parts as Blob, so multipart photos are sent as files.
import fs from "node:fs";
import path from "node:path";
import { pathToFileURL } from "node:url";
import ts from "typescript";
import openapiTS, { astToString } from "openapi-typescript";

const [input, output] = process.argv.slice(2);
const BLOB = ts.factory.createTypeReferenceNode(ts.factory.createIdentifier("Blob"));
const ast = await openapiTS(pathToFileURL(path.resolve(input)), {
  transform(schema) {
    if (schema.format === "binary") return BLOB;
  },
});
fs.writeFileSync(output, astToString(ast));
