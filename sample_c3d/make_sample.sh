#!/bin/sh
# Regenerates the bundled sample session (needs ICT-FaceKit, see README.md in this folder).
# Run from the repository root: sh sample_c3d/make_sample.sh
set -e
mocaptk synth sample_c3d/dense_halfface.c3d --half --spacing 8 --rig cara --seed 7 --noise 0.2 \
    --expressions 5 --rest 1.5 --hold 2.0 --performance 20 --dropout 0.01 --ghosts 0.002 \
    --max-gap 6 --quiet --force
