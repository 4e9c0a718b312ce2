"""What the add-on does to a Blender scene: key a Motion into a character (bake, keying,
retarget, preset, feet, visemes), keep it as a take, add its sound, write its report, and
build the demo speaker. It imports neither ui/ nor features/."""
