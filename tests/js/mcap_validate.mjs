// Reads an MCAP file with @mcap/core (as the Foxglove and Lichtblick apps do) and validates
// every JSON message against its channel's JSON schema with ajv (issue 38). Prints one JSON
// line: {json_messages, channels, invalid: {topic: first error}}.
import { McapIndexedReader } from "@mcap/core";
import { open } from "node:fs/promises";
import lz4 from "@foxglove/wasm-lz4";
import zstd from "@foxglove/wasm-zstd";
import Ajv2020 from "ajv/dist/2020.js";

await Promise.all([lz4.isLoaded, zstd.isLoaded]);
const decompressHandlers = {
  lz4: (buffer, size) => lz4(buffer, Number(size)),
  zstd: (buffer, size) => zstd.decompress(buffer, Number(size)),
};

const handle = await open(process.argv[2], "r");
const readable = {
  size: async () => BigInt((await handle.stat()).size),
  read: async (offset, length) => {
    const buf = new Uint8Array(Number(length));
    await handle.read(buf, 0, Number(length), Number(offset));
    return buf;
  },
};
const reader = await McapIndexedReader.Initialize({ readable, decompressHandlers });
const ajv = new Ajv2020({ strict: true, allErrors: false });
const validators = new Map();
const invalid = {};
let json_messages = 0;
const decoder = new TextDecoder();
for await (const msg of reader.readMessages()) {
  const channel = reader.channelsById.get(msg.channelId);
  const schema = reader.schemasById.get(channel.schemaId);
  if (!schema || schema.encoding !== "jsonschema") continue;
  let validate = validators.get(channel.id);
  if (!validate) {
    validate = ajv.compile(JSON.parse(decoder.decode(schema.data)));
    validators.set(channel.id, validate);
  }
  json_messages++;
  if (!validate(JSON.parse(decoder.decode(msg.data))) && !(channel.topic in invalid)) {
    const e = validate.errors[0];
    invalid[channel.topic] = `${e.instancePath || "<root>"}: ${e.message}`;
  }
}
await handle.close();
console.log(JSON.stringify({ json_messages, channels: reader.channelsById.size, invalid }));
