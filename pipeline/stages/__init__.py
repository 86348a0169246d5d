"""The stages: thin functions that find their inputs by key (:mod:`pipeline.keys`), call the
libraries and write one artifact each. A stage never imports another stage."""
