"""The training corpus of the bundled default model: synthetic English speech with exact
phone timings, augmented to sound like real recordings, and a teacher motion for every
utterance in the `beat` layout.

    python -m diffsheg_core.training.corpus build --out DIR --hours H

Modules: `texts` (Debian's fortunes as utterances), `synthesis` with `espeak`,
`festival` and `flite` (speech and timed phones), `phones` (the shared ARPAbet form, TextGrids),
`augment` (pitch, tempo, reverb, band limits, noise, level), `prosody` (accents),
`visemes` and `face` (the procedural face), `gestures` (phrases of the real capture placed
on accents), `teacher` (all of it as a Motion; utterance files), `build` (the parallel,
resumable builder).
"""
