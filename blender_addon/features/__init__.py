"""What the panel's buttons run, on top of scene/: Generate (generate.py), regenerating a
range with pins (regenerate.py), Live, Generate for Sound Strips (strips.py) and the
exports. It never imports ui/."""
