// An OPC 40100-1 client on another stack (node-opcua), knowing only the specification: it
// finds the vision system by its type definition, runs a continuous job with the
// specification's arguments, receives ResultReadyEvents, reads a missed result back, is
// refused a recipe switch while running, stops, switches the recipe. It prints one JSON line
// of what it saw and exits 0, or prints the failure and exits 1.
// Usage: node mv_client.cjs opc.tcp://127.0.0.1:PORT/cell   (NODE_PATH: node-opcua-client's folder)
"use strict";
const {
  OPCUAClient,
  BrowseDirection,
  DataType,
  VariantArrayType,
  makeBrowsePath,
  ClientSubscription,
  ClientMonitoredItem,
  constructEventFilter,
  TimestampsToReturn,
  AttributeIds,
  StatusCodes,
  resolveNodeId,
} = require("node-opcua-client");

const MV_URI = "http://opcfoundation.org/UA/MachineVision";
const endpoint = process.argv[2];

function check(condition, what) {
  if (!condition) throw new Error(`check failed: ${what}`);
}

async function sleep(ms) {
  return new Promise((resolve) => setTimeout(resolve, ms));
}

async function main() {
  const client = OPCUAClient.create({ endpointMustExist: false, connectionStrategy: { maxRetry: 3, initialDelay: 200 } });
  await client.connect(endpoint);
  const session = await client.createSession();
  try {
    return await flow(session);
  } finally {
    await session.close();
    await client.disconnect();
  }
}

async function target(session, start, path) {
  const res = await session.translateBrowsePath(makeBrowsePath(start, path));
  check(res.statusCode.isGood() && res.targets.length === 1, `browse path ${path}: ${res.statusCode.toString()}`);
  return res.targets[0].targetId.toString();
}

async function findByType(session, nodeId, typeId, depth) {
  const br = await session.browse({
    nodeId,
    referenceTypeId: "HierarchicalReferences",
    includeSubtypes: true,
    browseDirection: BrowseDirection.Forward,
    nodeClassMask: 1, // objects
    resultMask: 63,
  });
  for (const ref of br.references || []) {
    if (ref.typeDefinition.toString() === typeId) return ref.nodeId.toString();
  }
  if (depth > 0) {
    for (const ref of br.references || []) {
      const found = await findByType(session, ref.nodeId, typeId, depth - 1);
      if (found) return found;
    }
  }
  return null;
}

async function call(session, objectId, methodId, inputArguments) {
  const res = await session.call({ objectId, methodId, inputArguments });
  return res;
}

async function flow(session) {
  const namespaces = await session.readNamespaceArray();
  const mv = namespaces.indexOf(MV_URI);
  check(mv > 0, "the server has the Machine Vision namespace");
  const vsType = await target(session, "i=58", `/${mv}:VisionSystemType`); // BaseObjectType
  const vs = await findByType(session, "i=85", vsType, 2); // Objects
  check(vs, "an object of VisionSystemType under Objects");
  const sm = await target(session, vs, `/${mv}:VisionStateMachine`);
  const auto = await target(session, sm, `/${mv}:AutomaticModeStateMachine`);
  const results = await target(session, vs, `/${mv}:ResultManagement`);
  const recipes = await target(session, vs, `/${mv}:RecipeManagement`);
  const current = await target(session, auto, "/CurrentState");

  const dataType = async (path) => resolveNodeId(await target(session, "i=22", path)); // under Structure
  const ext = async (path, pojo) => ({
    dataType: DataType.ExtensionObject,
    value: await session.constructExtensionObject(await dataType(path), pojo),
  });

  // ResultReadyEvents from the vision system
  const resultReady = await target(session, "i=2041", `/${mv}:ResultReadyEventType`); // BaseEventType
  const fields = ["EventType", "Message", `${mv}:ResultId`, `${mv}:JobId`, `${mv}:ResultState`];
  const events = [];
  const subscription = ClientSubscription.create(session, {
    requestedPublishingInterval: 100,
    requestedMaxKeepAliveCount: 20,
    publishingEnabled: true,
  });
  const item = ClientMonitoredItem.create(
    subscription,
    { nodeId: vs, attributeId: AttributeIds.EventNotifier },
    { queueSize: 1000, filter: constructEventFilter(fields), discardOldest: false },
    TimestampsToReturn.Neither,
  );
  item.on("changed", (values) => {
    if (values[0].value.toString() === resultReady) {
      events.push({ resultId: values[2].value, jobId: values[3].value, state: values[4].value });
    }
  });
  await sleep(300);

  const start = await call(session, auto, await target(session, auto, `/${mv}:StartContinuous`), [
    await ext(`/${mv}:MeasIdDataType`, { id: "meas-node" }),
    await ext(`/${mv}:PartIdDataType`, { id: "part-node" }),
    await ext(`/${mv}:BinaryIdBaseDataType/${mv}:RecipeIdExternalDataType`, { id: "" }),
    await ext(`/${mv}:ProductIdDataType`, { id: "kit-node" }),
    { dataType: DataType.ExtensionObject, arrayType: VariantArrayType.Array, value: [] },
  ]);
  check(start.statusCode.isGood(), `StartContinuous: ${start.statusCode.toString()}`);
  const jobId = start.outputArguments[0].value.id;
  check(typeof jobId === "string" && jobId.length > 0, "StartContinuous gave a JobId");

  for (let i = 0; i < 100 && events.filter((e) => e.jobId && e.jobId.id === jobId).length < 2; i++) await sleep(100);
  const mine = events.filter((e) => e.jobId && e.jobId.id === jobId);
  check(mine.length >= 2, `ResultReadyEvents for the job (got ${mine.length})`);

  const got = await call(session, results, await target(session, results, `/${mv}:GetResultById`), [
    await ext(`/${mv}:ResultIdDataType`, { id: `${jobId}/1` }),
    { dataType: DataType.Int32, value: 2000 },
  ]);
  check(got.statusCode.isGood(), `GetResultById: ${got.statusCode.toString()}`);
  const result = got.outputArguments[1].value;
  check(result.resultId.id === `${jobId}/1`, "the result asked for");
  check(result.measId.id === "meas-node" && result.partId.id === "part-node", "MeasId and PartId carried into the result");

  const prepareId = await target(session, recipes, `/${mv}:PrepareRecipe`);
  const recipe = (id) => ext(`/${mv}:BinaryIdBaseDataType/${mv}:RecipeIdExternalDataType`, { id });
  const internal = (id) => ext(`/${mv}:BinaryIdBaseDataType/${mv}:RecipeIdInternalDataType`, { id });
  const refused = await call(session, recipes, prepareId, [await recipe("nuts-only"), await internal("")]);
  check(refused.statusCode.equals(StatusCodes.BadInvalidState), `PrepareRecipe while running: ${refused.statusCode.toString()}`);

  const stop = await call(session, auto, await target(session, auto, `/${mv}:Stop`), [
    { dataType: DataType.Int32, value: 0 },
    { dataType: DataType.String, value: "node-opcua test" },
  ]);
  check(stop.statusCode.isGood(), `Stop: ${stop.statusCode.toString()}`);
  let state = "";
  for (let i = 0; i < 100 && state !== "Ready"; i++) {
    state = (await session.read({ nodeId: current, attributeId: AttributeIds.Value })).value.value.text;
    if (state !== "Ready") await sleep(100);
  }
  check(state === "Ready", `back in Ready after Stop (${state})`);

  const prepared = await call(session, recipes, prepareId, [await recipe("nuts-only"), await internal("")]);
  check(prepared.statusCode.isGood(), `PrepareRecipe in Ready: ${prepared.statusCode.toString()}`);
  await subscription.terminate();
  return {
    jobId,
    events: mine.length,
    resultId: result.resultId.id,
    resultState: result.resultState,
    preparedInternalId: prepared.outputArguments[0].value.id,
    stateAfterStop: state,
  };
}

main()
  .then((summary) => {
    console.log(JSON.stringify(summary));
    process.exit(0);
  })
  .catch((err) => {
    console.error(`mv_client: ${err && err.stack ? err.stack : err}`);
    process.exit(1);
  });
