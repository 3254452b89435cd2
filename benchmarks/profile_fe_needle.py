"""cProfile of `needletissue fe needle --json [ARGS]` in one process with a CPU timer (docs/bench.md, "The default
`fe needle`: profile"). Prints parent and children (gmsh) CPU, wall, peak RSS and the top of the profile;
writes the stats to $PROF_OUT (default /tmp/profile_fe_needle.out).

    NEEDLETISSUE_MESH_CACHE=0 python benchmarks/profile_fe_needle.py
"""


def main():
    import cProfile, pstats, resource, sys, time, io, os
    t0 = time.process_time(); w0 = time.perf_counter()
    pr = cProfile.Profile(time.process_time)
    pr.enable()
    from needletissue import cli
    sys.argv = ["needletissue", "fe", "needle", "--json"] + sys.argv[1:]
    out = io.StringIO()
    real = sys.stdout
    sys.stdout = out
    try:
        cli.main()
    except SystemExit:
        pass
    finally:
        sys.stdout = real
    pr.disable()
    ru = resource.getrusage(resource.RUSAGE_SELF); rc = resource.getrusage(resource.RUSAGE_CHILDREN)
    print(f"parent CPU {time.process_time()-t0:.2f} s, children CPU {rc.ru_utime+rc.ru_stime:.2f} s, wall {time.perf_counter()-w0:.2f} s, peak RSS {ru.ru_maxrss/1024:.0f} MB")
    pr.dump_stats(os.environ.get("PROF_OUT", "/tmp/profile_fe_needle.out"))
    s = pstats.Stats(pr); s.sort_stats("cumulative").print_stats(60)


if __name__ == "__main__":
    main()
