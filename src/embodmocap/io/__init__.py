"""Reading and writing: session layout, atomic writes, captures, manifests, formats."""
