"""Training and its data: BVH+WAV folders -> training windows (`dataset`), audio augmentation (`augment`),
`dimgestor train` (`train`), and synthetic data where the answer is known (`synthetic`: tones; `voiceworld`:
espeak-ng voices)."""
