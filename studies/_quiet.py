"""Imported first by a study's forkserver (``studies.runner``): pybullet imported without its
build-time banner, before the preloaded study modules import it (the server printed it on
the study's standard error)."""

from studies.threads import quiet_pybullet

quiet_pybullet()
