"""The named scenes (TOML files beside this file), shipped with the project as package data:
``testbed scenes`` lists them; a bare name such as ``experiment2`` finds one."""
