"""The front ends: the command line (`apps.cli`) and the browser viewer (`apps.viewer`)."""
