// Reads an MCAP file the way Foxglove does: @mcap/core's indexed reader with @mcap/support's
// decompressors and protobuf descriptor loader; decodes every message with its channel's schema and
// checks it (a Foxglove message also against @foxglove/schemas' definition of its type). Prints one
// JSON object: per topic the schema name and encoding, the message count, and the first and last
// decoded message (for the Python test to compare with the session).
// Usage: node check.cjs FILE.mcap
"use strict";
const fs = require("fs");
const { McapIndexedReader } = require("@mcap/core");
const { loadDecompressHandlers, protobufFromBinaryDescriptor } = require("@mcap/support");
const wellKnown = require("@foxglove/schemas/jsonschema");

function fail(message) {
  process.stderr.write(message + "\n");
  process.exit(1);
}

// Foxglove Studio 1.x / Lichtblick accept one type per JSON Schema property.
function jsonDecoder(schema, topic) {
  const parsed = JSON.parse(new TextDecoder().decode(schema.data));
  const properties = parsed.properties || {};
  for (const [name, property] of Object.entries(properties)) {
    if (typeof property.type !== "string") fail(`${topic}: property ${name} has type ${JSON.stringify(property.type)}`);
  }
  const checks = { integer: Number.isInteger, number: (v) => typeof v === "number" && Number.isFinite(v),
                   string: (v) => typeof v === "string", boolean: (v) => typeof v === "boolean" };
  return (data) => {
    const message = JSON.parse(new TextDecoder().decode(data));
    for (const name of parsed.required || []) if (!(name in message)) fail(`${topic}: ${name} missing`);
    for (const [name, value] of Object.entries(message)) {
      const property = properties[name];
      if (!property) fail(`${topic}: field ${name} not in the schema`);
      if (!checks[property.type](value)) fail(`${topic}: ${name}=${JSON.stringify(value)} is not ${property.type}`);
    }
    return message;
  };
}

// A decoded protobuf message against @foxglove/schemas' own definition of its type (not the file's
// descriptor): the same fields, each of the type Foxglove declares. Protobuf carries a `time` as
// {seconds, nanos}, 64-bit integers as decimal strings and bytes as base64 strings.
function conform(value, definition, where) {
  const isInteger = (v) => Number.isInteger(v) || (typeof v === "string" && /^-?\d+$/.test(v));
  if (definition.title === "time" || definition.title === "duration") {
    if (!value || Object.keys(value).sort().join() !== "nanos,seconds" || !isInteger(value.seconds) ||
        !isInteger(value.nanos)) fail(`${where}: ${JSON.stringify(value)} is not a ${definition.title}`);
  } else if (definition.oneOf) {
    if (!definition.oneOf.some((option) => option.const === value)) fail(`${where}: ${value} is not one of ${definition.title}`);
  } else if (definition.type === "object") {
    const expected = Object.keys(definition.properties).sort().join();
    if (Object.keys(value).sort().join() !== expected) fail(`${where}: fields ${Object.keys(value)} are not ${expected}`);
    for (const [name, property] of Object.entries(definition.properties)) conform(value[name], property, `${where}.${name}`);
  } else if (definition.type === "array") {
    if (!Array.isArray(value)) fail(`${where}: not an array`);
    value.forEach((item, index) => conform(item, definition.items, `${where}[${index}]`));
  } else {
    const checks = { integer: isInteger, number: (v) => typeof v === "number", string: (v) => typeof v === "string",
                     boolean: (v) => typeof v === "boolean" };
    if (!checks[definition.type] || !checks[definition.type](value)) fail(`${where}: ${JSON.stringify(value)} is not ${definition.type}`);
  }
}

function protobufDecoder(schema, topic) {
  const shortName = schema.name.replace(/^foxglove\./, "");
  if (!schema.name.startsWith("foxglove.") || !wellKnown[shortName]) fail(`${topic}: ${schema.name} is not a Foxglove schema`);
  const type = protobufFromBinaryDescriptor(schema.data).lookupType(schema.name);
  return (data) => {
    const message = type.decode(data);
    const problem = type.verify(message);
    if (problem) fail(`${topic}: ${problem}`);
    const decoded = type.toObject(message, { longs: String, defaults: true, bytes: String, arrays: true });
    conform(decoded, wellKnown[shortName], topic);
    return decoded;
  };
}

async function main() {
  const path = process.argv[2];
  const handle = await fs.promises.open(path, "r");
  const size = (await handle.stat()).size;
  const readable = {
    size: async () => BigInt(size),
    read: async (offset, length) => {
      const buffer = new Uint8Array(Number(length));
      await handle.read(buffer, 0, Number(length), Number(offset));
      return buffer;
    },
  };
  const reader = await McapIndexedReader.Initialize({ readable, decompressHandlers: await loadDecompressHandlers() });
  const topics = {};
  const decoders = new Map();
  for (const channel of reader.channelsById.values()) {
    const schema = reader.schemasById.get(channel.schemaId);
    const decode = channel.messageEncoding === "json" && schema.encoding === "jsonschema" ? jsonDecoder(schema, channel.topic)
      : channel.messageEncoding === "protobuf" && schema.encoding === "protobuf" ? protobufDecoder(schema, channel.topic)
      : fail(`${channel.topic}: ${channel.messageEncoding}/${schema.encoding} is not a Foxglove encoding`);
    decoders.set(channel.id, decode);
    topics[channel.topic] = { schema: schema.name, encoding: channel.messageEncoding, count: 0, first: null, last: null,
                              first_log_time: null, metadata: Object.fromEntries(channel.metadata) };
  }
  for await (const message of reader.readMessages()) {
    const channel = reader.channelsById.get(message.channelId);
    const entry = topics[channel.topic];
    const decoded = decoders.get(message.channelId)(message.data);
    if (message.publishTime !== message.logTime) fail(`${channel.topic}: publish time differs from log time`);
    entry.count += 1;
    if (entry.first === null) { entry.first = decoded; entry.first_log_time = String(message.logTime); }
    entry.last = decoded;
  }
  const metadata = reader.metadataIndexes.map((index) => index.name);  // values are checked from Python
  process.stdout.write(JSON.stringify({ topics, metadata }) + "\n");
  await handle.close();
}

main().catch((error) => fail(String(error && error.stack || error)));
