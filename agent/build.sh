#!/usr/bin/env bash
# Build the capture agent (docs/phones.md). Every step writes below OUT (default agent/build).
#   agent/build.sh jar [OUT]    the JVM build: core + simulator platform, OUT/tbp-capture-agent-jvm.jar
#                               (what `tbp sim phone --agent-runtime jvm` runs with java)
#   agent/build.sh check [OUT]  compile the core and the Camera2 backend against agent/stubs, the
#                               Android API stubs (compile only: the classes are thrown away)
#   agent/build.sh test [OUT]   compile and run the core's JUnit 4 tests (Debian's junit4)
#   agent/build.sh dex [OUT]    with ANDROID_HOME: javac against the platform's android.jar, then d8:
#                               OUT/tbp-capture-agent.jar, the jar hardware.yaml's capture_agent names
#   agent/build.sh all [OUT]    jar, check and test; dex too when ANDROID_HOME is set
# Language level: Java 8 for everything that runs on a phone (d8 accepts it, and ART on Android 12+
# has all of Java 8's library); the simulator platform needs Java 17 (UNIX-domain sockets).
set -euo pipefail
HERE="$(cd "$(dirname "$0")" && pwd)"
STEP="${1:-all}"
OUT="$(mkdir -p "${2:-$HERE/build}" && cd "${2:-$HERE/build}" && pwd)"
JUNIT_JARS="/usr/share/java/junit4.jar:/usr/share/java/hamcrest-core.jar"

sources() { find "$HERE/$1" -name '*.java' | sort; }

compile() {  # compile DEST RELEASE CLASSPATH SOURCE_DIRS...: every lint warning is an error
    local dest="$1" release="$2" classpath="$3"
    shift 3
    rm -rf "$dest" && mkdir -p "$dest"
    local files=()
    for dir in "$@"; do mapfile -t -O "${#files[@]}" files < <(sources "$dir"); done
    javac -encoding UTF-8 ${LINT--Xlint:all -Werror} --release "$release" ${classpath:+-cp "$classpath"} \
        -d "$dest" "${files[@]}"
}

jar_step() {
    compile "$OUT/classes/core" 8 "" src/core
    compile "$OUT/classes/jvm" 17 "$OUT/classes/core" src/jvm
    rm -f "$OUT/tbp-capture-agent-jvm.jar"
    jar --create --file "$OUT/tbp-capture-agent-jvm.jar" --main-class com.tbp.CaptureAgent \
        -C "$OUT/classes/core" . -C "$OUT/classes/jvm" .
    echo "$OUT/tbp-capture-agent-jvm.jar"
}

check_step() {
    LINT="" compile "$OUT/classes/stubs" 8 "" stubs  # the SDK's shapes, not this project's code
    compile "$OUT/classes/android-check" 8 "$OUT/classes/stubs" src/core src/android
    rm -rf "$OUT/classes/stubs" "$OUT/classes/android-check"
    echo "Camera2 backend compiles against agent/stubs"
}

test_step() {
    for jar in ${JUNIT_JARS//:/ }; do
        [ -f "$jar" ] || { echo "missing $jar: apt-get install junit4" >&2; exit 1; }
    done
    compile "$OUT/classes/core" 8 "" src/core
    compile "$OUT/classes/test" 8 "$OUT/classes/core:$JUNIT_JARS" test
    local tests=()
    mapfile -t tests < <(cd "$OUT/classes/test" && find . -name '*Test.class' | sed 's|^\./||; s|\.class$||; s|/|.|g' | sort)
    java -cp "$OUT/classes/core:$OUT/classes/test:$JUNIT_JARS" org.junit.runner.JUnitCore "${tests[@]}"
}

dex_step() {
    : "${ANDROID_HOME:?set ANDROID_HOME to the Android SDK (platforms/android-NN, build-tools/X)}"
    local platform="${ANDROID_PLATFORM:-$(ls "$ANDROID_HOME/platforms" | sed 's/^android-//' | sort -n | tail -1)}"
    local tools="${ANDROID_BUILD_TOOLS:-$(ls "$ANDROID_HOME/build-tools" | sort -V | tail -1)}"
    local android_jar="$ANDROID_HOME/platforms/android-$platform/android.jar"
    local d8="$ANDROID_HOME/build-tools/$tools/d8"
    [ -f "$android_jar" ] || { echo "no $android_jar" >&2; exit 1; }
    [ -x "$d8" ] || { echo "no $d8" >&2; exit 1; }
    local dest="$OUT/classes/android"
    rm -rf "$dest" && mkdir -p "$dest"
    local files=()
    mapfile -t files < <(sources src/core; sources src/android)
    # -bootclasspath: java.* resolve against Android's library, not the JDK's.
    javac -encoding UTF-8 -source 8 -target 8 -bootclasspath "$android_jar" -d "$dest" "${files[@]}"
    local classes=()
    mapfile -t classes < <(find "$dest" -name '*.class' | sort)
    rm -f "$OUT/tbp-capture-agent.jar"
    "$d8" --release --min-api 31 --lib "$android_jar" --output "$OUT/tbp-capture-agent.jar" "${classes[@]}"
    echo "$OUT/tbp-capture-agent.jar (android-$platform, build-tools $tools)"
}

cd "$HERE"
case "$STEP" in
    jar) jar_step ;;
    check) check_step ;;
    test) test_step ;;
    dex) dex_step ;;
    all)
        jar_step
        check_step
        test_step
        if [ -n "${ANDROID_HOME:-}" ]; then dex_step; else echo "ANDROID_HOME unset: no dex jar (see docs/phones.md)"; fi
        ;;
    *) echo "usage: agent/build.sh jar|check|test|dex|all [OUT]" >&2; exit 2 ;;
esac
