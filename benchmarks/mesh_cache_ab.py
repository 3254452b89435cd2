"""The default `fe needle` mesh: gmsh in its child process (cache off) against a mesh-cache hit, CPU of the
process and its children and wall, alternating (docs/bench.md).

    python benchmarks/mesh_cache_ab.py
"""


def main():
    import resource, time, tempfile, os
    from pathlib import Path
    from needletissue.geometry.needle import NeedleGeometry, mesh_needle_model
    def cpu():
        a = resource.getrusage(resource.RUSAGE_SELF); b = resource.getrusage(resource.RUSAGE_CHILDREN)
        return a.ru_utime + a.ru_stime + b.ru_utime + b.ru_stime
    g = NeedleGeometry()
    with tempfile.TemporaryDirectory() as tmp:
        for rep in range(2):
            for cache in (False, True):
                c, w = cpu(), time.perf_counter()
                info = mesh_needle_model(g, Path(tmp) / f"m{rep}{cache}.msh", order=2, cache=cache)
                print(f"cache={cache} cached={info.cached}: CPU {cpu() - c:.2f} s wall {time.perf_counter() - w:.2f} s, {info.tetrahedra} tets", flush=True)
        print("same file:", (Path(tmp) / "m0False.msh").read_bytes() == (Path(tmp) / "m0True.msh").read_bytes())


if __name__ == "__main__":
    main()
