"""The paper's classical baseline: (G)ICP pose graph (``registration``), then Poisson meshing with
label transfer (``poisson``). Open3D is the optional extra ``fleetmap[baseline]``, imported lazily."""
