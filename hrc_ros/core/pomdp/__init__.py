"""The hidden part of the cell (MODEL.md 6, docs/POMDP.md): the belief filter over the human's
emotions (`belief`), the point-based solver over the belief (`solver`, backups in `_kernels`)
and its alpha-vector policy files (`policy`)."""
