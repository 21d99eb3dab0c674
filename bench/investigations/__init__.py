"""Investigations: each answered one question once (most justify one constant of the product).

They are kept runnable (``python -m bench.investigations.<name>``) so that the answer can be
checked again when what it rests on changes; ``README.md`` beside this file says, per script, the
question, the answer and where the result is recorded. The maintained benchmarks (the
``python -m bench`` suite, the product against the user's own loop, the service's figures) are in
``bench/``.
"""
