"""The pipeline model: the YAML file with positions, operator params, validation and the graph."""
