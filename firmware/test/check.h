// A minimal test harness for the native tests: TEST registers a case, CHECK* record failures and go on.
#pragma once
#include <math.h>
#include <stdio.h>

namespace check {

typedef void (*TestFn)();
struct Case {
    const char* name;
    TestFn fn;
};

inline Case* cases() {
    static Case all[256];
    return all;
}
inline int& case_count() {
    static int count = 0;
    return count;
}
inline int& failures() {
    static int count = 0;
    return count;
}

struct Registrar {
    Registrar(const char* name, TestFn fn) { cases()[case_count()++] = Case{name, fn}; }
};

// Run every registered case; the exit status is the number of failed checks (capped at 1).
inline int run_all(const char* suite) {
    for (int i = 0; i < case_count(); ++i) {
        int before = failures();
        cases()[i].fn();
        printf("%s %s\n", failures() == before ? "ok  " : "FAIL", cases()[i].name);
    }
    printf("%s: %d cases, %d failed checks\n", suite, case_count(), failures());
    return failures() ? 1 : 0;
}

}  // namespace check

#define TEST(name)                                                     \
    static void name();                                                \
    static check::Registrar registrar_##name(#name, name);             \
    static void name()

#define CHECK(cond)                                                                         \
    do {                                                                                    \
        if (!(cond)) {                                                                      \
            fprintf(stderr, "%s:%d: CHECK(%s) failed\n", __FILE__, __LINE__, #cond);        \
            ++check::failures();                                                            \
        }                                                                                   \
    } while (0)

#define CHECK_EQ(a, b)                                                                                  \
    do {                                                                                                \
        long long check_a = (long long)(a), check_b = (long long)(b);                                   \
        if (check_a != check_b) {                                                                       \
            fprintf(stderr, "%s:%d: CHECK_EQ(%s, %s) failed: %lld != %lld\n", __FILE__, __LINE__, #a, #b, \
                    check_a, check_b);                                                                  \
            ++check::failures();                                                                        \
        }                                                                                               \
    } while (0)

#define CHECK_NEAR(a, b, tolerance)                                                                          \
    do {                                                                                                     \
        double check_a = (double)(a), check_b = (double)(b);                                                 \
        if (!(fabs(check_a - check_b) <= (tolerance))) {                                                     \
            fprintf(stderr, "%s:%d: CHECK_NEAR(%s, %s, %s) failed: %g vs %g\n", __FILE__, __LINE__, #a, #b,  \
                    #tolerance, check_a, check_b);                                                           \
            ++check::failures();                                                                             \
        }                                                                                                    \
    } while (0)
