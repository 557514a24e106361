import servobench as sb
with sb.open_drive("sim://") as drive:        # any URL; stops and closes the axis on exit, also on errors
    result = sb.sidbe(drive, out="run")       # the whole procedure, as the CLI's sidbe
log = sb.read_log("run/log.csv")              # sb.Log: runs as numpy arrays, metadata
model = sb.identify(log)                      # sb.Model: M, B, coulomb_pos, coulomb_neg, std, units, delay
report = sb.diagnose(log)                     # .verdict, .effects, .model, .gap_percent, .noise_floor_percent
check = sb.validate(model, log)               # .verdict, .fit_percent, .gap_percent
values = sb.program(model)                    # the values to program, as `servobench program` gives them
v = model.simulate(log.runs[0].u, fs=1000.0)  # velocity for a command sequence
model.save("model.json"); same = sb.load_model("model.json")
