"""The command lines: thin orchestration over core, io and eval (see kentreg_ros.cli.common)."""
