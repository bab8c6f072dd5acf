"""Files and pictures: EXR/PNG/MP4/JSON and atomic folders, DNG raw files, matplotlib drawing, HTML pieces."""
