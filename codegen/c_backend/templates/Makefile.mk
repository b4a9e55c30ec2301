# {notice}
# Builds the flight bundle with only a C99 compiler and libm (make -j to compile units in parallel):
#   make            lib{model}.so and lib{model}.a (double)
#   make float      lib{model}_float.a (casadi_real = float, -DSYMKF_FLOAT)
#   make stack      {model}_stack.ci: GCC's call graphs with stack frames (the header's *_STACK_BYTES)
CC ?= cc
OPT ?= {optimization}
CFLAGS ?= {strict_flags} $(OPT)
LDLIBS = -lm
OBJECTS = {objects}
FLOAT_OBJECTS = {float_objects}
STACK_OBJECTS = {stack_objects}

all: lib{model}.so lib{model}.a

lib{model}.so: $(OBJECTS)
	$(CC) -shared -o $@.tmp $(OBJECTS) $(LDLIBS) && mv -f $@.tmp $@

lib{model}.a: $(OBJECTS)
	$(AR) rcs $@ $(OBJECTS)

float: lib{model}_float.a

lib{model}_float.a: $(FLOAT_OBJECTS)
	$(AR) rcs $@ $(FLOAT_OBJECTS)

stack: $(STACK_OBJECTS)
	cat $(STACK_OBJECTS:.o=.ci) > {model}_stack.ci

{rules}
clean:
	rm -f *.o *.a *.tmp *.su *.ci

.PHONY: all float stack clean
